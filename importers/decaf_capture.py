"""The capture stage's DECAF importer (a helper of ``stages.capture``, not a stage).

Reads one subject of the DECAF release (layout and format: :mod:`importers.decaf`) into the
capture layout (:mod:`data_schemas.capture`):

* DECAF ``train``/``test`` -> sequences ``train``/``test`` (the paper's self-reenactment split);
* ``cameras.pkl`` -> ``cameras.parquet`` (``dataset.test_cameras`` held out for novel views);
* videos -> ``<seq>/videos/<camera>.mp4`` (a copy, never a link; re-encoded when frames are skipped or
  the container is not mp4);
* segmentation mattes -> part masks: matte foreground inside the grown hull of the provided hand
  keypoints is hand (2), the rest face (1);
* ``head_keys`` (68 iBUG landmarks) and ``right_hand_keys`` (21) -> ``provided/keypoints.parquet``;
* ``params_smoothed.pkl`` -> ``provided/params.parquet`` and ``deforms.npy`` ->
  ``provided/deform.parquet``, both only with the official FLAME and MANO files (model.flame_path,
  model.mano_path): DECAF's numbers index the official models' components, and its head pose turns
  about the mesh centroid, which only the model gives (:mod:`avatar.templates.decaf`);
* contacts -> ``provided/contacts.parquet``.

What DECAF ships but is not imported is said in ``SequenceInfo.notes``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from avatar.preprocess.masks import label_parts
from avatar.templates import OfficialModelError, TemplateModel, load_official_model, procedural_head
from avatar.templates.decaf import decaf_hand_to_mano, decaf_head_to_flame, decaf_world_offsets
from avatar.templates.layers import OPENPOSE_FROM_MANO
from avatar.templates.loaders import ModelKind
from data_schemas.cameras import Camera, write_cameras
from data_schemas.capture import CaptureIndex, SequenceInfo, copy_into_capture, mask_path, provided_path, video_path
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.images import write_png
from data_schemas.keypoints import write_keypoints
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import SchemaError, write_table
from data_schemas.video import iter_video, write_video_stream
from importers.decaf import (
    MODES,
    DecafParams,
    DecafSequence,
    camera_key,
    decaf_cameras,
    iter_matte,
    read_contacts,
    read_deforms,
    read_keypoints,
    read_neck_vertices,
    read_params,
    scan_sequence,
)
from importers.frame_selection import selected_frames

HAND_ORDERS = ("mediapipe", "mano")


@dataclass(frozen=True)
class _Models:
    """The official head (FLAME) and hand (MANO) models; None where model.flame_path / mano_path is unset."""

    head: TemplateModel | None
    hand: TemplateModel | None


def decaf_subject_problem(root: Path, subject: str) -> str | None:
    """Why the DECAF release at ``root`` has no ``subject`` to import (its ``train/videos/<subject>`` folder is
    missing), naming the subjects it has; None when it has."""
    if (root / "train" / "videos" / subject).is_dir():
        return None
    on_disk = sorted(p.name for p in (root / "train" / "videos").glob("*") if p.is_dir())
    return (
        f"{root / 'train' / 'videos' / subject}: missing; set dataset.root to the unpacked "
        f"DecafDataset folder and subject to one of {on_disk or 'its subjects'}"
    )


def import_decaf(dataset: DictConfig, subject: str, out: Path, default_frame_rate: float) -> CaptureIndex:
    """Validate and import ``subject`` of the DECAF release at ``dataset.root`` into ``out``."""
    root = Path(dataset.root)
    if dataset.subjects is not None and subject not in dataset.subjects:
        raise SchemaError(f"subject={subject!r} is not in dataset.subjects {list(dataset.subjects)}")
    if dataset.hand_keypoint_order not in HAND_ORDERS:
        raise SchemaError(f"dataset.hand_keypoint_order={dataset.hand_keypoint_order!r}: choose one of {HAND_ORDERS}")
    problem = decaf_subject_problem(root, subject)
    if problem is not None:
        raise SchemaError(problem)
    scans = {
        mode: scan_sequence(root, mode, subject)
        for mode in MODES
        if mode == "train" or (root / mode / "videos" / subject).is_dir()
    }
    cameras = _cameras(scans, dataset.test_cameras)
    models = _Models(head=_official(dataset.flame_path, "flame"), hand=_official(dataset.mano_path, "mano"))
    sequences = {
        mode: _import_sequence(scan, out, cameras, models, dataset, default_frame_rate) for mode, scan in scans.items()
    }
    write_cameras(out / "cameras.parquet", cameras)
    return CaptureIndex(subject=subject, dataset="decaf", sequences=sequences)


def _official(path: str | None, kind: ModelKind) -> TemplateModel | None:
    if not path:
        return None
    try:
        return load_official_model(path, kind)
    except OfficialModelError as exc:
        raise SchemaError(str(exc)) from exc


def _cameras(scans: dict[str, DecafSequence], test_cameras: list[str] | None) -> list[Camera]:
    """One calibration for both splits (the capture layout has one per camera): they must agree."""
    ids = sorted(scans["train"].videos)
    held_out = [str(c) for c in test_cameras] if test_cameras is not None else ids[-1:]
    known = {camera_key(c) for c in ids}
    if any(camera_key(c) not in known for c in held_out) or len({camera_key(c) for c in held_out}) >= len(ids):
        raise SchemaError(f"dataset.test_cameras={held_out}: choose some but not all of the cameras {ids}")
    cameras = decaf_cameras(scans["train"], set(held_out))
    for mode, scan in scans.items():
        if mode == "train":
            continue
        other = {c.camera_id: c for c in decaf_cameras(scan, set(held_out))}
        if sorted(other) != ids:
            raise SchemaError(
                f"{scan.root / mode / 'videos' / scan.subject}: cameras {sorted(other)} differ from "
                f"train's {ids}; the capture layout needs the same cameras in every sequence"
            )
        for cam in cameras:
            o = other[cam.camera_id]
            if (o.width, o.height) != (cam.width, cam.height) or not (
                np.allclose(o.K, cam.K, rtol=1e-6, atol=1e-6)
                and np.allclose(o.world_to_cam, cam.world_to_cam, rtol=1e-6, atol=1e-6)
            ):
                raise SchemaError(
                    f"{scan.cameras_pkl}: camera '{cam.camera_id}' differs from "
                    f"{scans['train'].cameras_pkl} (or its video size does); the capture layout "
                    f"holds one calibration per camera"
                )
    return cameras


def _import_sequence(
    scan: DecafSequence,
    out: Path,
    cameras: list[Camera],
    models: _Models,
    dataset: DictConfig,
    default_frame_rate: float,
) -> SequenceInfo:
    seq = scan.mode
    frames = selected_frames(scan.num_frames, dataset, f"{scan.root}/{seq}: sequence of subject {scan.subject}")
    notes: list[str] = []
    provided: list[str] = []
    keypoints = _read_keypoints(scan, cameras, frames, dataset.hand_keypoint_order)
    params = read_params(scan) if scan.params_pkl.is_file() else None
    contacts = read_contacts(scan, frames) if scan.folder("contacts").is_dir() else None
    if params is None:
        notes.append(f"{_rel(scan.params_pkl, scan)} missing: no provided params or deformations")
    if keypoints:
        write_keypoints(provided_path(out, seq, "keypoints"), keypoints, len(frames))
        provided.append("keypoints")
    else:
        notes.append(
            f"no {_rel(scan.folder('head_keys'), scan)} or {_rel(scan.folder('right_hand_keys'), scan)}: "
            f"no provided keypoints"
        )
    if params is not None:
        selected = params.select(frames)
        if _write_params(provided_path(out, seq, "params"), scan, selected, models, notes):
            provided.append("params")
        contact = None if contacts is None else np.asarray(contacts[0].any(axis=1))
        if scan.deforms_npy.is_file() and _write_deform(
            provided_path(out, seq, "deform"), scan, frames, selected, contact, models, notes
        ):
            provided.append("deform")
    if contacts is not None:
        face, hand = contacts
        write_table(
            provided_path(out, seq, "contacts"),
            CONTACTS,
            {"frame": np.arange(len(frames)), "contact": face.any(axis=1), "face": face, "hand": hand},
        )
        provided.append("contacts")
    fps = (scan.frame_rate or float(default_frame_rate)) / int(dataset.frame_step)
    for cam in cameras:
        _import_video(scan, cam.camera_id, frames, video_path(out, seq, cam.camera_id), fps)
        if scan.has_segmentations:
            hands = keypoints.get(cam.camera_id, {}).get("hand")
            _import_masks(scan, cam.camera_id, frames, out, hands, float(dataset.hand_mask_margin))
    if not scan.has_segmentations:
        notes.append(f"no {_rel(scan.folder('segmentations'), scan)}: the frames stage keys the background")
    return SequenceInfo(
        num_frames=len(frames),
        frame_rate=fps,
        width=cameras[0].width,
        height=cameras[0].height,
        has_masks=scan.has_segmentations,
        has_ground_truth=False,
        provided=tuple(provided),
        notes=tuple(notes),
    )


def _rel(path: Path, scan: DecafSequence) -> Path:
    """A path inside the release, relative to its root: notes do not depend on where the data lies."""
    return path.relative_to(scan.root)


# ---------------------------------------------------------------------------- keypoints
def _read_keypoints(
    scan: DecafSequence, cameras: list[Camera], frames: np.ndarray, hand_order: str
) -> dict[str, dict[str, np.ndarray]]:
    """camera id -> part -> (T, K, 3) for the parts the dataset ships."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for cam in cameras:
        for part in ("hand", "face"):
            if scan.has_keypoints(part):
                kp = read_keypoints(scan, part, cam.camera_id, frames)
                out.setdefault(cam.camera_id, {})[part] = (
                    kp[:, list(OPENPOSE_FROM_MANO)] if part == "hand" and hand_order == "mano" else kp
                )
    return out


# ---------------------------------------------------------------------------- params and deformations
def _write_params(path: Path, scan: DecafSequence, params: DecafParams, models: _Models, notes: list[str]) -> bool:
    if models.head is None or models.hand is None:
        notes.append(
            f"{_rel(scan.params_pkl, scan)} not imported: DECAF's FLAME/MANO parameters need the "
            f"official models; set model.flame_path (FLAME 2020 generic_model.pkl) and "
            f"model.mano_path (MANO_RIGHT.pkl)"
        )
        return False
    try:
        columns = {
            **decaf_head_to_flame(
                models.head,
                params.head_shape,
                params.head_expression,
                params.head_pose,
                params.head_global_orient,
                params.head_transl,
            ),
            **decaf_hand_to_mano(
                models.hand, params.hand_betas, params.hand_pose, params.hand_global_orient, params.hand_transl
            ),
        }
    except ValueError as exc:
        raise SchemaError(f"{scan.params_pkl}: {exc}") from exc
    write_table(path, PARAMS, {"frame": np.arange(len(params.head_transl)), **{k: columns[k] for k in PARAM_COLUMNS}})
    return True


def _write_deform(
    path: Path,
    scan: DecafSequence,
    frames: np.ndarray,
    params: DecafParams,
    contact: np.ndarray | None,
    models: _Models,
    notes: list[str],
) -> bool:
    """Only when the deformations have one offset per vertex of the configured head model. ``contact``
    (T,) from the shipped contacts; without them, frames with any non-zero offset."""
    deforms = read_deforms(scan, frames)
    vertices = deforms.shape[1]
    head = models.head or procedural_head()
    if head.num_vertices != vertices:
        which = "the official head model" if models.head else "the procedural head (model.flame_path unset)"
        notes.append(
            f"{_rel(scan.deforms_npy, scan)} not imported: {vertices} vertices, but {which} has "
            f"{head.num_vertices}; set model.flame_path to the official FLAME 2020 generic_model.pkl "
            f"(5023 vertices)"
        )
        return False
    neck = read_neck_vertices(scan.root)
    if neck is not None:
        deforms[:, neck[(neck >= 0) & (neck < vertices)]] = 0.0  # as DECAF's scripts do
    offsets = decaf_world_offsets(deforms, params.head_global_orient)
    if contact is None:
        contact = np.abs(offsets).reshape(len(frames), -1).max(axis=1) > 0
    write_table(
        path, DEFORM, {"frame": np.arange(len(frames)), "contact": contact, "offsets": offsets.reshape(len(frames), -1)}
    )
    return True


# ---------------------------------------------------------------------------- videos and masks
def _import_video(scan: DecafSequence, camera_id: str, frames: np.ndarray, dst: Path, fps: float) -> None:
    src = scan.videos[camera_id]
    if len(frames) == scan.num_frames and src.suffix.lower() == ".mp4":
        copy_into_capture(src, dst)
        return
    wanted = set(frames.tolist())
    written = write_video_stream(dst, (f for t, f in enumerate(iter_video(src)) if t in wanted), fps)
    if written != len(frames):
        raise SchemaError(
            f"{src}: decoded too few frames for the {len(frames)} selected (of {scan.num_frames} the "
            f"container announces); the video is truncated or corrupt"
        )


def _import_masks(
    scan: DecafSequence, camera_id: str, frames: np.ndarray, out: Path, hands: np.ndarray | None, margin: float
) -> None:
    index = {int(t): i for i, t in enumerate(frames)}
    written = 0
    for t, matte in enumerate(iter_matte(scan, camera_id)):
        if t not in index:
            continue
        i = index[t]
        points = None if hands is None else hands[i, hands[i, :, 2] > 0, :2]
        write_png(mask_path(out, scan.mode, camera_id, i), label_parts(matte, points, margin))
        written += 1
    if written != len(frames):
        raise SchemaError(
            f"{scan.segmentation(camera_id)}: decoded {written} of the {len(frames)} selected frames; "
            f"the segmentation video is truncated or corrupt"
        )
