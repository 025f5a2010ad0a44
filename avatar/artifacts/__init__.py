"""Readers and writers of the artifacts several stages share: parameter tables, contact labels, the pbd stage's
offsets, the frames stage's crops, the scene decisions and world-space PLY frames (not a stage itself: stages
still talk only through artifacts)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatar.device import fits_on_device, host
from avatar.geometry.views import ViewSet
from avatar.render.gaussians import WorldGaussians
from avatar.scene import SceneDecision
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, SequenceInfo, gt_path, provided_path
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.frames import FRAMES_INDEX, crop_mask_path, rgb_path
from data_schemas.gaussians_ply import GaussianCloud, write_gaussians_ply
from data_schemas.images import read_png
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import SchemaError, read_table, write_table


def load_ground_truth_params(capture_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The capture's ground-truth FLAME/MANO parameters of ``sequence``."""
    index = CaptureIndex.read(capture_dir)
    if not index.sequences[sequence].has_ground_truth:
        raise SchemaError(
            f"{capture_dir}: fit.source=ground_truth needs a capture with ground truth "
            f"(dataset=synthetic); this one has none"
        )
    table = read_table(gt_path(capture_dir, sequence, "params"), PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


def load_provided_params(capture_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The FLAME/MANO parameters the dataset ships for ``sequence`` (DECAF's multi-view fit)."""
    index = CaptureIndex.read(capture_dir)
    info = index.sequences[sequence]
    if not info.has_provided("params"):
        why = "".join(f"; {note}" for note in info.notes if "param" in note)
        raise SchemaError(
            f"{capture_dir / sequence}: fit.source=provided needs parameters shipped with the dataset "
            f"(dataset=decaf), but the '{index.dataset}' capture of '{index.subject}' has none for "
            f"sequence '{sequence}'{why}"
        )
    table = read_table(provided_path(capture_dir, sequence, "params"), PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


GROUND_TRUTH_CONTACTS = "ground truth"


SHIPPED_CONTACTS = "shipped with the dataset"


def contact_source(info: SequenceInfo) -> str | None:
    """Where a sequence's contact labels come from: :data:`GROUND_TRUTH_CONTACTS` (the generator's),
    :data:`SHIPPED_CONTACTS` (e.g. DECAF's) or None (no labels)."""
    if info.has_ground_truth:
        return GROUND_TRUTH_CONTACTS
    return SHIPPED_CONTACTS if info.has_provided("contacts") else None


def contact_frames(capture_dir: Path, sequence: str, num_frames: int) -> np.ndarray:
    """(T,) bool: frames where the hand touches the face, from ground truth or the contacts the dataset
    ships (:func:`contact_source`); all False when unknown."""
    source = contact_source(CaptureIndex.read(capture_dir).sequences[sequence])
    if source == GROUND_TRUTH_CONTACTS:
        return np.asarray(read_table(gt_path(capture_dir, sequence, "deform"), DEFORM)["contact"], dtype=bool)
    if source == SHIPPED_CONTACTS:
        return np.asarray(read_table(provided_path(capture_dir, sequence, "contacts"), CONTACTS)["contact"], dtype=bool)
    return np.zeros(num_frames, dtype=bool)


def load_params(fit_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The fit stage's per-frame FLAME/MANO parameters of ``sequence`` (the columns of ``params.parquet``)."""
    return read_params(fit_dir / sequence / "params.parquet")


def contact_flags(pbd_dir: Path, sequence: str, num_frames: int) -> np.ndarray:
    """(T,) bool: frames in which the pbd stage found the hand touching the face (``deform.parquet``)."""
    path = pbd_dir / sequence / "deform.parquet"
    contact = np.asarray(read_table(path, DEFORM)["contact"], dtype=bool)
    if contact.shape != (num_frames,):
        raise SchemaError(f"{path}: {contact.shape[0]} frames, expected {num_frames}; rerun the pbd stage")
    return contact


TRAIN_SEQUENCE = "train"
#: the held-out motion (reenact.sequence names it by default; a capture of one's own may lack it)
HELD_OUT_SEQUENCE = "test"


def method_params(trained_dir: Path, fit_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The parameters a trained method poses ``sequence`` with: for the train motion, those its training refined
    (``params.parquet`` of its warmup or dynamic stage ``trained_dir``; the fit's where it refined nothing); for
    any other sequence the fit's (the held-out motion is never refined against its images)."""
    if sequence != TRAIN_SEQUENCE:
        return load_params(fit_dir, sequence)
    return read_params(trained_dir / "params.parquet")


def read_params(path: Path) -> dict[str, np.ndarray]:
    """The FLAME/MANO columns of a ``params.parquet``."""
    table = read_table(path, PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


def write_params(path: Path, params: dict[str, np.ndarray]) -> None:
    """``params.parquet`` of T frames (:data:`PARAMS`; the inverse of :func:`read_params`)."""
    num_frames = len(params["flame_global_orient"])
    write_table(path, PARAMS, {"frame": np.arange(num_frames), **{k: params[k] for k in PARAM_COLUMNS}})


def load_face_offsets(pbd_dir: Path, sequence: str, num_frames: int, num_vertices: int) -> np.ndarray:
    """(T, V, 3) contact offsets of the face from the pbd stage's ``deform.parquet``: world frame, metres,
    *added* to the posed face (DECAF's canonical, subtracted offsets are converted when imported)."""
    path = pbd_dir / sequence / "deform.parquet"
    offsets = np.asarray(read_table(path, DEFORM)["offsets"], dtype=np.float64)
    if offsets.shape != (num_frames, num_vertices * 3):
        raise SchemaError(
            f"{path}: offsets of shape {offsets.shape}, expected ({num_frames}, {num_vertices * 3}) "
            f"for {num_frames} frames of a {num_vertices}-vertex head; rerun the pbd stage"
        )
    return offsets.reshape(num_frames, num_vertices, 3)


def load_views(
    capture_dir: Path, frames_dir: Path, sequence: str, split: str, device: torch.device | str = "cpu"
) -> ViewSet:
    """The crops of ``sequence`` seen by the cameras of ``split`` (``train`` or ``test``), loaded once onto ``device``
    (a clear MemoryError where they would take more of a GPU than :func:`avatar.device.fits_on_device` allows)."""
    index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    cameras = {c.camera_id: c for c in read_cameras(capture_dir / "cameras.parquet") if c.split == split}
    rows = [
        i
        for i, (seq, cam) in enumerate(zip(index["sequence"], index["camera_id"]))
        if seq == sequence and cam in cameras
    ]
    if not rows:
        raise SchemaError(f"{frames_dir / 'index.parquet'}: no crops of sequence '{sequence}' for split '{split}'")
    camera_ids = sorted(cameras)
    frames = sorted({int(index["frame"][i]) for i in rows})
    K = {index["camera_id"][i]: index["K"][i].reshape(3, 3) for i in rows}
    images = np.stack(
        [np.stack([read_png(rgb_path(frames_dir, sequence, c, t), 3) for c in camera_ids]) for t in frames]
    )
    labels = np.stack(
        [np.stack([read_png(crop_mask_path(frames_dir, sequence, c, t), 1) for c in camera_ids]) for t in frames]
    )
    background = (
        images[labels == 0].reshape(-1, 3).astype(np.float64).mean(0) / 255.0 if (labels == 0).any() else np.zeros(3)
    )
    fits_on_device(
        images.nbytes + labels.nbytes,
        device,
        f"the {len(frames)} frames x {len(camera_ids)} cameras of {sequence}/{split} crops in {frames_dir}",
        "lower quality.image_size or the capture's frame count, or train with run.device=cpu",
    )
    return ViewSet(
        images=torch.from_numpy(images),
        labels=torch.from_numpy(labels),
        K=torch.tensor(np.stack([K[c] for c in camera_ids]), dtype=torch.float32),
        world_to_cam=torch.tensor(np.stack([cameras[c].world_to_cam for c in camera_ids]), dtype=torch.float32),
        camera_ids=camera_ids,
        background=torch.tensor(background, dtype=torch.float32),
    ).to(device)


def load_scene(scene_dir: Path) -> SceneDecision:
    """The scene stage's decisions (``scene.json``): what the downstream stages model, and why."""
    info = json.loads((scene_dir / "scene.json").read_text())
    return SceneDecision(
        bool(info["model_hand"]), bool(info["model_pbd"]), bool(info["model_interaction"]), dict(info["why"])
    )


@dataclass
class PosedGaussians:
    """World-space Gaussians of one frame (a :class:`WorldGaussians`): means (N, 3), scales (N, 3), quats (N, 4),
    opacities (N,), colors (N, 3)."""

    means: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


def write_frame_ply(path: Path, g: WorldGaussians) -> None:
    """World-space 3DGS PLY of one frame's Gaussians (``means``, ``scales``, ``quats``, ``opacities``,
    ``colors`` attributes, e.g. an :class:`avatar.dynamic.DynamicFrame`)."""
    with torch.no_grad():
        o = g.opacities.clamp(1e-6, 1 - 1e-6)
        write_gaussians_ply(
            path,
            GaussianCloud.from_rgb(
                host(g.means),
                host(torch.log(g.scales)),
                host(g.quats),
                host(torch.log(o / (1 - o))),
                host(g.colors),
            ),
        )
