"""Reader of the public DECAF dataset layout (Shimada et al., "Decaf: Monocular Deformation Capture
for Face and Hand Interactions", SIGGRAPH Asia 2023). The dataset is licensed and never shipped.

Layout, per DECAF split ``<mode>`` (``train``/``test``), subject ``<S>`` (``S1`` ...) and camera ``<C>``
(``084``, ``100``, ...)::

    <root>/<mode>/videos/<S>/<C>.mp4               RGB video per camera (1920x1080 in the release)
    <root>/<mode>/segmentations/<S>/<C>.mp4        foreground matte as a video, same frames (optional)
    <root>/<mode>/head_keys/<S>/<C>.npy            (N, 68, >=2) face landmarks, px (optional)
    <root>/<mode>/right_hand_keys/<S>/<C>.npy      (N, 21, >=2) right-hand keypoints, px (optional)
    <root>/<mode>/cameras/<S>/cameras.pkl          {<C>: {"intrinsic": (3, 3), "extrinsic": (4, 4)}}
    <root>/<mode>/params/<S>/params_smoothed.pkl   {frame: {"head": {...}, "right_hand": {...}}} (optional)
    <root>/<mode>/deformations/<S>/deforms.npy     (N, 5023, 3) FLAME-canonical offsets (optional)
    <root>/<mode>/contacts/<S>/contacts_head.npy   (N, 5023) and contacts_rh.npy (N, 778) (optional)
    <root>/assets/FLAME_neck_idx.npy               vertices whose deformation DECAF's scripts zero (optional)

Confirmed from the dataset's public scripts (github.com/soshishimada/DecafDatasetScript:
``visualizer.py``, ``flipping_data.py``, ``get_masked_image.py``, ``src/util.py``) and the DECAF
loader of DICE (github.com/Qingxuan-Wu/DICE, ``src/decaf/simple_data_loader.py``):

* the paths above; one video, segmentation video and keypoint file per camera, named by the camera
  id; ``cameras.pkl`` maps the camera id (zero-padded, ``"084"``) to ``intrinsic`` (3x3, pixels) and
  ``extrinsic`` (4x4 world-to-camera; DECAF projects with ``intrinsic @ extrinsic[:3]``);
* segmentations are grey mattes thresholded at 127 (foreground of the whole person, not parts);
* ``params_smoothed.pkl`` holds one entry per video frame, sorted by key; ``head``: ``shape_params``
  (100), ``expression_params`` (50), ``pose_params`` (6: FLAME root then jaw axis-angle),
  ``global_orient`` (3), ``transl`` (3); ``right_hand``: ``betas`` (10), ``hand_pose`` (45
  axis-angle: DECAF builds MANO with 45 PCA components, which turns PCA off, and a flat hand mean),
  ``global_orient`` (3), ``transl`` (3);
* ``deforms.npy`` are in FLAME's canonical frame: DECAF rotates them by the head ``global_orient``
  and *subtracts* them from the posed head; contacts are per-vertex flags of the head and hand;
* keypoint files have one row per frame; DECAF's scripts use only columns 0 and 1 (pixels).

Not confirmed (choices made here, each failing with one clear message when the data disagree):

* the distortion coefficients' key in ``cameras.pkl`` (the README says they exist; the scripts never
  read them): any of :data:`DISTORTION_KEYS` is read, none means no distortion;
* what columns past the second of a keypoint file mean and how a failed detection is stored:
  columns >= 2 are ignored; a keypoint that is not finite, lies outside the image, or belongs to an
  all-zero detection gets confidence 0, every other one 1;
* the order of the 21 hand keypoints: MediaPipe's (wrist, then thumb, index, middle, ring and pinky
  from base to tip), which is this project's order; ``hand_keypoint_order=mano`` in the dataset
  config reads MANO's joint order plus tips instead (the order of DECAF's own MANO keypoints);
* that the video container's frame count is right (videos are only decoded when re-encoded).

Everything here is numpy and OpenCV; converting parameters to this project's FLAME/MANO convention
needs the template models and lives in :mod:`avatar.templates.decaf`.
"""

from __future__ import annotations

import codecs
import pickle
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from data_schemas.cameras import Camera, check_camera
from data_schemas.tables import SchemaError
from data_schemas.video import iter_video, video_fps, video_frame_count

MODES = ("train", "test")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
KEYPOINT_FOLDERS = {"face": "head_keys", "hand": "right_hand_keys"}
KEYPOINT_COUNTS = {"face": 68, "hand": 21}
DISTORTION_KEYS = ("distortion", "dist", "dist_coeffs", "distortion_coefficients")
MATTE_THRESHOLD = 127  # DECAF's get_masked_image.py: foreground where the matte exceeds 127


# ---------------------------------------------------------------------------- pickles
def _numpy_allow_list() -> dict[tuple[str, str], Any]:
    try:  # numpy >= 2 keeps the array machinery in numpy._core
        from numpy._core import multiarray, numeric
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray, numeric  # type: ignore[no-redef]
    # Protocol 2, written by Python 3, stores an array's bytes as _codecs.encode(<latin1 text>, "latin1"):
    # a pure conversion from text to bytes, so it is safe to allow.
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("collections", "OrderedDict"): OrderedDict,
        ("_codecs", "encode"): codecs.encode,
    }
    for package in ("numpy.core", "numpy._core"):
        allowed[(f"{package}.multiarray", "_reconstruct")] = multiarray._reconstruct
        allowed[(f"{package}.multiarray", "scalar")] = multiarray.scalar
        # ignore: numpy's stubs omit the private _frombuffer, which pickled arrays name
        allowed[(f"{package}.numeric", "_frombuffer")] = numeric._frombuffer  # type: ignore[attr-defined]
    return allowed


class _DataUnpickler(pickle.Unpickler):
    """Materialises only builtin containers and numpy arrays: a pickle can run no code."""

    allowed = _numpy_allow_list()

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.allowed:
            return self.allowed[(module, name)]
        raise pickle.UnpicklingError(f"holds a {module}.{name}; expected only dicts, lists and numpy arrays")


def load_pickle(path: Path) -> Any:
    """A DECAF pickle (dicts, lists, numpy arrays; Python 2 or 3), or one clear error."""
    if not path.is_file():
        raise SchemaError(f"{path}: missing; the DECAF layout needs it (see importers/decaf.py)")
    try:
        with path.open("rb") as stream:
            return _DataUnpickler(stream, encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise SchemaError(f"{path}: not a readable DECAF pickle ({exc})") from exc


def _array(path: Path, where: str, value: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape`` (None: any length), or one clear error."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{path}: {where} is not numeric ({exc})") from exc
    if arr.ndim == len(shape) + 1 and arr.shape[0] == 1:  # (1, D) per-frame values, as torch code keeps them
        arr = arr[0]
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise SchemaError(f"{path}: {where} has shape {arr.shape}, expected {want}")
    if not np.isfinite(arr).all():
        raise SchemaError(f"{path}: {where} contains NaN or Inf")
    return arr


# ---------------------------------------------------------------------------- one sequence
@dataclass(frozen=True)
class DecafSequence:
    """One DECAF split (``mode``) of one subject, scanned and cross-checked (see :func:`scan_sequence`)."""

    root: Path
    mode: str
    subject: str
    videos: dict[str, Path]  # camera id (the video's stem) -> video file
    num_frames: int
    frame_rate: float  # from the first video's container; 0 when it carries none
    sizes: dict[str, tuple[int, int]]  # camera id -> (width, height)

    def folder(self, kind: str) -> Path:
        """``<root>/<mode>/<kind>/<subject>``, e.g. ``kind="head_keys"``."""
        return self.root / self.mode / kind / self.subject

    @property
    def cameras_pkl(self) -> Path:
        return self.folder("cameras") / "cameras.pkl"

    @property
    def params_pkl(self) -> Path:
        return self.folder("params") / "params_smoothed.pkl"

    @property
    def deforms_npy(self) -> Path:
        return self.folder("deformations") / "deforms.npy"

    def segmentation(self, camera_id: str) -> Path:
        return self.folder("segmentations") / self.videos[camera_id].name

    def keypoints_file(self, part: str, camera_id: str) -> Path:
        return self.folder(KEYPOINT_FOLDERS[part]) / f"{camera_id}.npy"

    def contacts_file(self, part: str) -> Path:
        return self.folder("contacts") / ("contacts_head.npy" if part == "face" else "contacts_rh.npy")

    @property
    def has_segmentations(self) -> bool:
        return self.folder("segmentations").is_dir()

    def has_keypoints(self, part: str) -> bool:
        return self.folder(KEYPOINT_FOLDERS[part]).is_dir()


def ships_keypoints(root: str | Path, subject: str) -> bool:
    """Whether the DECAF release at ``root`` has keypoint files for ``subject`` (``<mode>/head_keys/<subject>/`` or
    ``<mode>/right_hand_keys/<subject>/`` of either split): they are optional in the release."""
    base = Path(root)
    return any((base / mode / part / subject).is_dir() for mode in MODES for part in ("head_keys", "right_hand_keys"))


def camera_key(camera_id: str) -> str:
    """Numeric ids match by value (``84`` is ``084``), others literally."""
    return str(int(camera_id)) if camera_id.isdigit() else camera_id


def read_calibration(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """``cameras.pkl`` -> camera id -> ``K`` (3, 3), ``world_to_cam`` (4, 4), ``dist`` (D,)."""
    data = load_pickle(path)
    if not isinstance(data, dict) or not data:
        raise SchemaError(
            f"{path}: expected a dict camera id -> {{'intrinsic', 'extrinsic'}}, "
            f"found {type(data).__name__}{' (empty)' if isinstance(data, dict) else ''}"
        )
    out: dict[str, dict[str, np.ndarray]] = {}
    for key, entry in data.items():
        cam = str(key)
        if not isinstance(entry, dict) or "intrinsic" not in entry or "extrinsic" not in entry:
            found = sorted(map(str, entry)) if isinstance(entry, dict) else type(entry).__name__
            raise SchemaError(
                f"{path}: camera '{cam}' needs keys 'intrinsic' (3x3) and 'extrinsic' "
                f"(4x4 world-to-camera), found {found}"
            )
        dist_key = next((k for k in DISTORTION_KEYS if k in entry), None)
        out[cam] = {
            "K": _array(path, f"camera '{cam}' intrinsic", entry["intrinsic"], (3, 3)),
            "world_to_cam": _array(path, f"camera '{cam}' extrinsic", entry["extrinsic"], (4, 4)),
            "dist": (
                _array(path, f"camera '{cam}' {dist_key}", np.ravel(entry[dist_key]), (None,))
                if dist_key
                else np.zeros(5)
            ),
        }
    return out


def _probe(path: Path) -> tuple[int, int, int]:
    """(frames by the container, width, height) of a video, decoding one frame."""
    cap = cv2.VideoCapture(str(path))
    try:
        ok, frame = cap.read()
    finally:
        cap.release()
    if not ok:
        raise SchemaError(f"{path}: no decodable frames (corrupt or not a video); re-export it as mp4")
    return video_frame_count(path), frame.shape[1], frame.shape[0]


def scan_sequence(root: Path, mode: str, subject: str) -> DecafSequence:
    """Cross-check one split of a subject: every video has a camera in cameras.pkl and every camera a
    video; views, segmentations and keypoint files agree on frame count and size."""
    videos_dir = root / mode / "videos" / subject
    if not videos_dir.is_dir():
        raise SchemaError(
            f"{videos_dir}: missing; DECAF keeps one video per camera in <root>/{mode}/videos/<subject>/<camera>.mp4"
        )
    videos = {p.stem: p for p in sorted(videos_dir.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES}
    if not videos:
        raise SchemaError(f"{videos_dir}: no videos ({', '.join(VIDEO_SUFFIXES)}); expected <camera>.mp4 per camera")
    seq = DecafSequence(root=root, mode=mode, subject=subject, videos=videos, num_frames=0, frame_rate=0.0, sizes={})
    calibrated = {camera_key(c) for c in read_calibration(seq.cameras_pkl)}
    without_camera = [c for c in videos if camera_key(c) not in calibrated]
    if without_camera:
        raise SchemaError(
            f"{videos[without_camera[0]]}: video has no camera '{without_camera[0]}' in "
            f"{seq.cameras_pkl}; add its calibration or remove the video"
        )
    without_video = sorted(calibrated - {camera_key(c) for c in videos})
    if without_video:
        raise SchemaError(
            f"{seq.cameras_pkl}: camera '{without_video[0]}' has no video in {videos_dir}; "
            f"add <camera>.mp4 or remove the camera"
        )
    probes = {cam: _probe(path) for cam, path in videos.items()}
    counts = {cam: p[0] for cam, p in probes.items()}
    if len(set(counts.values())) != 1 or 0 in counts.values():
        raise SchemaError(
            f"{videos_dir}: views disagree on frame count {counts}; DECAF's videos of one "
            f"subject are synchronised, re-export them from the release"
        )
    num_frames = next(iter(counts.values()))
    seq = DecafSequence(
        root=root,
        mode=mode,
        subject=subject,
        videos=videos,
        num_frames=num_frames,
        frame_rate=video_fps(next(iter(videos.values()))),
        sizes={cam: (p[1], p[2]) for cam, p in probes.items()},
    )
    if seq.has_segmentations:
        for cam in videos:
            frames, width, height = _probe(seq.segmentation(cam)) if seq.segmentation(cam).is_file() else (-1, 0, 0)
            if frames < 0:
                raise SchemaError(
                    f"{seq.segmentation(cam)}: missing; every camera needs a segmentation video "
                    f"(or remove {seq.folder('segmentations')} to key the background instead)"
                )
            if (frames, width, height) != (num_frames, *seq.sizes[cam]):
                raise SchemaError(
                    f"{seq.segmentation(cam)}: {frames} frames of {width}x{height}, but the video has "
                    f"{num_frames} of {seq.sizes[cam][0]}x{seq.sizes[cam][1]}"
                )
    for part in KEYPOINT_FOLDERS:
        if seq.has_keypoints(part):
            for cam in videos:
                _keypoint_array(seq.keypoints_file(part, cam), part, num_frames)
    return seq


def decaf_cameras(seq: DecafSequence, test_cameras: set[str]) -> list[Camera]:
    """The cameras of ``seq`` (ids = video stems, sorted), ``split="test"`` for ``test_cameras``."""
    calib = {camera_key(c): v for c, v in read_calibration(seq.cameras_pkl).items()}
    held_out = {camera_key(c) for c in test_cameras}
    width = max(len(v["dist"]) for v in calib.values())
    cameras = []
    for cam in sorted(seq.videos):
        c = calib[camera_key(cam)]
        dist = np.concatenate([c["dist"], np.zeros(width - len(c["dist"]))])
        camera = Camera(
            cam,
            *seq.sizes[cam],
            K=c["K"],
            world_to_cam=c["world_to_cam"],
            dist=dist,
            split="test" if camera_key(cam) in held_out else "train",
        )
        check_camera(seq.cameras_pkl, camera)
        cameras.append(camera)
    return cameras


# ---------------------------------------------------------------------------- per-frame data
def _keypoint_array(path: Path, part: str, num_frames: int) -> np.ndarray:
    if not path.is_file():
        raise SchemaError(f"{path}: missing; {path.parent} needs one <camera>.npy per video")
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SchemaError(f"{path}: not a readable .npy array ({exc})") from exc
    k = KEYPOINT_COUNTS[part]
    if arr.ndim != 3 or arr.shape[0] != num_frames or arr.shape[1] != k or arr.shape[2] < 2:
        raise SchemaError(
            f"{path}: shape {arr.shape}, expected ({num_frames}, {k}, 2 or more): one row per "
            f"video frame, {k} {part} keypoints, pixel u and v first"
        )
    return arr


def read_keypoints(seq: DecafSequence, part: str, camera_id: str, frames: np.ndarray) -> np.ndarray:
    """(len(frames), K, 3) float32 (u, v, confidence) of the selected ``frames`` (see the module
    docstring for how confidence is set)."""
    path = seq.keypoints_file(part, camera_id)
    uv = np.asarray(_keypoint_array(path, part, seq.num_frames)[frames, :, :2], dtype=np.float64)
    width, height = seq.sizes[camera_id]
    finite = np.asarray(np.isfinite(uv).all(axis=-1))
    inside = finite & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)
    detected = np.abs(np.where(np.isfinite(uv), uv, 0.0)).reshape(len(uv), -1).max(axis=1) > 0
    conf = (inside & detected[:, None]).astype(np.float64)
    return np.concatenate([np.where(finite[..., None], uv, 0.0), conf[..., None]], axis=-1).astype(np.float32)


@dataclass(frozen=True)
class DecafParams:
    """``params_smoothed.pkl`` as (N, D) float64 arrays, frames in key order."""

    head_shape: np.ndarray  # shape_params
    head_expression: np.ndarray  # expression_params
    head_pose: np.ndarray  # pose_params: FLAME root (3) then jaw (3), axis-angle
    head_global_orient: np.ndarray  # rotation about the mesh centroid (see avatar.templates.decaf)
    head_transl: np.ndarray
    hand_betas: np.ndarray
    hand_pose: np.ndarray  # 45 axis-angle (15 finger joints), flat hand mean
    hand_global_orient: np.ndarray
    hand_transl: np.ndarray

    def select(self, frames: np.ndarray) -> DecafParams:
        return DecafParams(**{f.name: getattr(self, f.name)[frames] for f in fields(self)})


_PARAM_KEYS = {  # field -> (part, key in the pickle, width or None)
    "head_shape": ("head", "shape_params", None),
    "head_expression": ("head", "expression_params", None),
    "head_pose": ("head", "pose_params", 6),
    "head_global_orient": ("head", "global_orient", 3),
    "head_transl": ("head", "transl", 3),
    "hand_betas": ("right_hand", "betas", None),
    "hand_pose": ("right_hand", "hand_pose", 45),
    "hand_global_orient": ("right_hand", "global_orient", 3),
    "hand_transl": ("right_hand", "transl", 3),
}


def _frame_order(keys: list[Any]) -> list[Any]:
    """Frame keys sorted numerically when they are numbers (or digit strings), else as DECAF sorts them."""
    if all(isinstance(k, (int, np.integer)) or (isinstance(k, str) and k.isdigit()) for k in keys):
        return sorted(keys, key=int)
    return sorted(keys)


def read_params(seq: DecafSequence) -> DecafParams:
    """``params_smoothed.pkl``: one entry per video frame, or one clear error naming the frame and key."""
    path = seq.params_pkl
    data = load_pickle(path)
    if not isinstance(data, dict):
        raise SchemaError(
            f"{path}: expected a dict frame -> {{'head': ..., 'right_hand': ...}}, found {type(data).__name__}"
        )
    if len(data) != seq.num_frames:
        raise SchemaError(
            f"{path}: {len(data)} frames, but the videos of {seq.mode}/{seq.subject} have "
            f"{seq.num_frames}; use the params file that belongs to these videos"
        )
    columns: dict[str, list[np.ndarray]] = {name: [] for name in _PARAM_KEYS}
    for key in _frame_order(list(data)):
        entry = data[key]
        for name, (part, field_name, width) in _PARAM_KEYS.items():
            where = f"frame {key!r} {part}.{field_name}"
            try:
                value = entry[part][field_name]
            except (KeyError, TypeError, IndexError):
                raise SchemaError(
                    f"{path}: frame {key!r} lacks {part}.{field_name}; each frame needs 'head' "
                    f"(shape_params, expression_params, pose_params, global_orient, transl) and "
                    f"'right_hand' (betas, hand_pose, global_orient, transl)"
                ) from None
            arr = _array(path, where, value, (width,))
            if columns[name] and len(arr) != len(columns[name][0]):
                raise SchemaError(f"{path}: {where} has {len(arr)} values, earlier frames {len(columns[name][0])}")
            columns[name].append(arr)
    return DecafParams(**{name: np.stack(rows) for name, rows in columns.items()})


def read_deforms(seq: DecafSequence, frames: np.ndarray) -> np.ndarray:
    """(len(frames), V, 3) float64 canonical offsets of the selected frames."""
    path = seq.deforms_npy
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SchemaError(f"{path}: not a readable .npy array ({exc})") from exc
    if arr.ndim != 3 or arr.shape[0] != seq.num_frames or arr.shape[2] != 3:
        raise SchemaError(f"{path}: shape {arr.shape}, expected ({seq.num_frames}, V, 3): one row per video frame")
    out = np.asarray(arr[frames], dtype=np.float64)
    if not np.isfinite(out).all():
        raise SchemaError(f"{path}: contains NaN or Inf")
    return out


def read_contacts(seq: DecafSequence, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex contact flags of the selected frames: face (T, V_head), hand (T, V_hand), bool."""
    out = []
    for part in ("face", "hand"):
        path = seq.contacts_file(part)
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise SchemaError(
                f"{path}: missing or not a readable .npy array ({exc}); {path.parent} needs "
                f"contacts_head.npy and contacts_rh.npy"
            ) from exc
        if arr.ndim != 2 or arr.shape[0] != seq.num_frames:
            raise SchemaError(
                f"{path}: shape {arr.shape}, expected ({seq.num_frames}, vertices): one row of "
                f"per-vertex flags per video frame"
            )
        out.append(np.asarray(arr[frames]) != 0)
    return out[0], out[1]


def read_neck_vertices(root: Path) -> np.ndarray | None:
    """``assets/FLAME_neck_idx.npy``: FLAME vertices whose deformation DECAF's scripts set to zero."""
    path = root / "assets" / "FLAME_neck_idx.npy"
    if not path.is_file():
        return None
    try:
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.int64).ravel()
    except (OSError, ValueError) as exc:
        raise SchemaError(f"{path}: not a readable .npy array of vertex ids ({exc})") from exc


def iter_matte(seq: DecafSequence, camera_id: str) -> Iterator[np.ndarray]:
    """Foreground of each frame of a camera's segmentation video, (H, W) bool."""
    for frame in iter_video(seq.segmentation(camera_id)):
        yield cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) > MATTE_THRESHOLD
