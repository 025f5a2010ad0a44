"""``dataset=folder``: validate a capture on disk and import it into the ``capture`` stage.

Layout (docs/how-to/real-footage.md): ``<root>/<subject>/<sequence>/videos/<camera_id>.mp4``, or an image folder
per camera, ``<sequence>/images/<camera_id>/*.png`` (or ``.jpg``; frames in name order, as many capture rigs and
COLMAP workflows write them), and optionally ``<sequence>/masks/``, with one calibration beside the sequences
(``dataset.calibration``):

* ``cameras.parquet`` (``parquet``): this project's own, in metres;
* a COLMAP sparse model (``colmap``): ``cameras.bin``/``images.bin`` or ``.txt``, in the subject folder,
  ``sparse/0/`` or ``sparse/``; image names map to cameras by folder or stem (``importers.calibrated_images``);
* a nerfstudio ``transforms.json`` (``nerfstudio``);
* ``auto`` (default): the first of these that exists.

COLMAP's and nerfstudio's scale is arbitrary: ``dataset.calibration_scale_m`` (metres per unit) scales the
translations; unset, the fit stage measures the face and names the scale to set. Distortion is removed
here, once: distorted views are re-encoded undistorted with the same ``K`` (and their masks remapped), so
every later stage sees pinhole cameras; ``calibration.json`` keeps the coefficients that were removed.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from avatar.calibration.undistort import Undistorter, is_distorted
from data_schemas.cameras import Camera, read_cameras, write_cameras
from data_schemas.capture import CaptureIndex, SequenceInfo, copy_into_capture, mask_path, video_path
from data_schemas.images import read_png, write_png
from data_schemas.names import camera_id_problem, folder_name_problem
from data_schemas.tables import SchemaError
from data_schemas.video import check_fully_decoded, iter_video, video_fps, write_video_stream
from data_schemas.writes import write_json
from importers.calibrated_images import rig_cameras
from importers.colmap import find_model, read_colmap
from importers.frame_selection import selected_frames
from importers.nerfstudio import read_transforms

CALIBRATIONS = ("auto", "parquet", "colmap", "nerfstudio")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEFAULT_INTRINSICS = "none: default intrinsics"  # source of a single uncalibrated camera (dataset.default_fov_deg)
PARQUET_HELP = (
    "cameras.parquet, one row per camera (camera_id, width, height, K, world_to_cam, dist, split; "
    "data_schemas.cameras.write_cameras writes it), a COLMAP sparse model or a nerfstudio transforms.json"
)


@dataclass(frozen=True)
class ViewSource:
    """One camera's frames of a sequence on disk: ``<sequence>/videos/<camera_id>.mp4`` or the images of
    ``<sequence>/images/<camera_id>/`` in name order."""

    path: Path

    @property
    def is_video(self) -> bool:
        return self.path.suffix.lower() == ".mp4"

    def images(self) -> list[Path]:
        return sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)

    def frames(self) -> Iterator[np.ndarray]:
        """(H, W, 3) uint8 RGB frames, one at a time."""
        if self.is_video:
            yield from iter_video(self.path)
            return
        for image in self.images():
            yield read_png(image, 3)

    def frame_rate(self) -> float | None:
        """Frames per second where the source says (a video's header); None for images."""
        return video_fps(self.path) if self.is_video else None


def view_sources(sequence_dir: Path) -> dict[str, ViewSource]:
    """camera_id -> its frames in ``sequence_dir``: the videos of ``videos/``, else the image folders of
    ``images/`` (a sequence has one kind; both is one clear error)."""
    videos = sequence_dir / "videos"
    images = sequence_dir / "images"
    if videos.is_dir() and images.is_dir():
        raise SchemaError(f"{sequence_dir}: has both videos/ and images/; keep one source of frames per sequence")
    if videos.is_dir():
        return {p.stem: ViewSource(p) for p in sorted(videos.iterdir()) if p.suffix.lower() == ".mp4"}
    if images.is_dir():
        return {p.name: ViewSource(p) for p in sorted(images.iterdir()) if p.is_dir()}
    return {}


def _is_sequence(path: Path) -> bool:
    return (path / "videos").is_dir() or (path / "images").is_dir()


def subject_folder_problem(src: Path, subject: str) -> str | None:
    """Why the subject folder ``src`` (``<dataset.root>/<subject>``) cannot be imported because it is not there."""
    if src.is_dir():
        return None
    return f"{src}: capture folder missing; set dataset.root so that <root>/{subject} exists"


def name_problems(src: Path) -> list[str]:
    """The sequence folders and camera names (video stems, image folders) of the capture folder ``src`` that
    cannot name artifact paths (:mod:`data_schemas.names`), one line each naming the file and the fix; read from
    the folder listing alone, so the config check runs it before any stage."""
    problems = []
    for seq in sorted(p for p in src.iterdir() if _is_sequence(p)) if src.is_dir() else ():
        if (problem := folder_name_problem(seq.name)) is not None:
            problems.append(f"{seq}: sequence folder {seq.name!r}: {problem} (rename the folder)")
            continue
        try:
            views = view_sources(seq)
        except SchemaError:  # both videos/ and images/: the capture stage says so
            continue
        for camera_id, view in views.items():
            if (problem := camera_id_problem(camera_id)) is not None:
                noun = "video" if view.is_video else "image folder"
                problems.append(f"{view.path}: camera id {camera_id!r} (the {noun}'s name): {problem}")
    return problems


def import_folder(dataset: DictConfig, subject: str, out: Path, default_frame_rate: float) -> CaptureIndex:
    """Validate ``<dataset.root>/<subject>`` and bring it into ``out`` (copies, or undistorted re-encodes)."""
    src = Path(dataset.root) / subject
    problem = subject_folder_problem(src, subject)
    if problem is not None:
        raise SchemaError(problem)
    if not any(src.iterdir()):
        raise SchemaError(
            f"{src}: capture folder is empty; put {PARQUET_HELP} and one video per camera in "
            f"<sequence>/videos/<camera_id>.mp4 in it, as in docs/reference/artifacts.md"
        )
    problems = name_problems(src)
    if problems:
        raise SchemaError("; ".join(problems))
    cameras, calibration = read_calibration(src, dataset)
    seq_names = sorted(p.name for p in src.iterdir() if _is_sequence(p))
    if not seq_names:
        raise SchemaError(
            f"{src}: no <sequence>/videos/ or <sequence>/images/ folder; put one video per camera in "
            f"e.g. {src}/train/videos/<camera_id>.mp4, or one image folder per camera in "
            f"{src}/train/images/<camera_id>/"
        )
    selections = {
        name: _validate_sequence(src, name, cameras, calibration, dataset, default_frame_rate) for name in seq_names
    }
    write_cameras(out / "cameras.parquet", [replace(c, dist=np.zeros_like(c.dist)) for c in cameras])
    for cam in cameras:
        undistort = Undistorter(cam.K, cam.dist, cam.width, cam.height) if is_distorted(cam.dist) else None
        for name, (info, frames) in selections.items():
            _import_view(src, out, name, cam, info, frames, undistort)
    defaulted = calibration == DEFAULT_INTRINSICS
    write_json(
        out / "calibration.json",
        {
            "source": calibration,
            "default_fov_deg": float(dataset.get("default_fov_deg", 60.0)) if defaulted else None,
            "scale_m": dataset.get("calibration_scale_m"),
            "undistorted": {c.camera_id: c.dist.tolist() for c in cameras if is_distorted(c.dist)},
        },
        "calibration record",
    )
    return CaptureIndex(
        subject=subject, dataset="folder", sequences={name: info for name, (info, _) in selections.items()}
    )


def read_calibration(src: Path, dataset: DictConfig) -> tuple[list[Camera], str]:
    """The cameras of the capture folder ``src`` (translations in metres when a scale is given) and where they
    came from: the calibration file or folder, or :data:`DEFAULT_INTRINSICS`."""
    choice = str(dataset.get("calibration", "auto"))
    if choice not in CALIBRATIONS:
        raise SchemaError(f"dataset.calibration={choice!r}: choose one of {CALIBRATIONS}")
    scale = dataset.get("calibration_scale_m")
    test_cameras = dataset.get("test_cameras")
    parquet, model, transforms = src / "cameras.parquet", find_model(src), src / "transforms.json"
    if choice == "auto":
        choice = (
            "parquet"
            if parquet.is_file()
            else "colmap"
            if model is not None
            else "nerfstudio"
            if transforms.is_file()
            else ""
        )
        if not choice:
            camera = _default_camera(src, float(dataset.get("default_fov_deg", 60.0)))
            if camera is None:
                raise SchemaError(
                    f"{src}: camera calibration missing; add {PARQUET_HELP} (only a single camera, a "
                    f"monocular video, may go without one)"
                )
            return [camera], DEFAULT_INTRINSICS
    if choice == "parquet":
        if not parquet.is_file():
            raise SchemaError(f"{parquet}: camera calibration missing; add {PARQUET_HELP}")
        cameras = read_cameras(parquet)
        if scale is not None:
            cameras = [replace(c, world_to_cam=_scaled(c.world_to_cam, float(scale))) for c in cameras]
        return cameras, str(parquet)
    if choice == "colmap":
        if model is None:
            raise SchemaError(f"{src}: no COLMAP model (cameras.bin or cameras.txt) in it, sparse/0/ or sparse/")
        images, where = read_colmap(model), model
    else:
        if not transforms.is_file():
            raise SchemaError(f"{transforms}: missing; dataset.calibration=nerfstudio reads it")
        images, where = read_transforms(transforms), transforms
    cameras = rig_cameras(
        images,
        str(where),
        1.0 if scale is None else float(scale),
        None if test_cameras is None else [str(c) for c in test_cameras],
    )
    return cameras, str(where)


def _default_camera(src: Path, fov_deg: float) -> Camera | None:
    """The one camera of a monocular capture without calibration: a pinhole with ``fov_deg`` horizontal field of
    view, principal point at the image centre, no distortion, at the world origin (world = camera axes).
    None when the folder has more than one camera (a rig needs its calibration)."""
    sources = [
        (cam_id, view)
        for seq in sorted(src.iterdir())
        if _is_sequence(seq)
        for cam_id, view in view_sources(seq).items()
    ]
    ids = sorted({cam_id for cam_id, _ in sources})
    if len(ids) != 1:
        return None
    if not 1.0 <= fov_deg <= 170.0:
        raise SchemaError(f"dataset.default_fov_deg={fov_deg}: a horizontal field of view in degrees, 1 to 170")
    first = next(sources[0][1].frames())
    height, width = first.shape[:2]
    focal = (width / 2) / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(
        camera_id=ids[0], width=width, height=height, K=K, world_to_cam=np.eye(4), dist=np.zeros(5), split="train"
    )


def _scaled(world_to_cam: np.ndarray, scale: float) -> np.ndarray:
    out = world_to_cam.copy()
    out[:3, 3] *= scale
    return out


def _import_view(
    src: Path,
    out: Path,
    seq: str,
    cam: Camera,
    info: SequenceInfo,
    frames: np.ndarray | None,
    undistort: Undistorter | None,
) -> None:
    """Copy one camera's video (and masks) of ``seq``, or encode the selected source ``frames`` (T,; None:
    all; from a video or an image folder), undistorted where the camera is distorted."""
    view = view_sources(src / seq)[cam.camera_id]
    sources = np.arange(info.num_frames) if frames is None else frames
    if undistort is None and frames is None and view.is_video:
        copy_into_capture(view.path, video_path(out, seq, cam.camera_id))
    else:
        wanted = set(sources.tolist())
        decoded = itertools.islice(view.frames(), int(sources[-1]) + 1)  # nothing past the last one
        kept = (f for t, f in enumerate(decoded) if t in wanted)
        write_video_stream(
            video_path(out, seq, cam.camera_id),
            kept if undistort is None else (undistort.image(f) for f in kept),
            info.frame_rate,
        )
    if not info.has_masks:
        return
    for t, source_t in enumerate(sources):
        source, target = mask_path(src, seq, cam.camera_id, int(source_t)), mask_path(out, seq, cam.camera_id, t)
        if undistort is None:
            copy_into_capture(source, target)
        else:
            write_png(target, undistort.labels(read_png(source, 1)))


def _scan(view: ViewSource) -> tuple[int, tuple[int, int]]:
    """Frame count and (height, width) of a view, decoded once, one frame at a time (a long recording never
    sits in memory); one clear error when a file is damaged, an image folder is empty or its images differ in
    size."""
    if not view.is_video and not view.images():
        raise SchemaError(
            f"{view.path}: image folder without {'/'.join(IMAGE_SUFFIXES)} images; put the camera's "
            f"frames in it (name order is frame order) or remove the folder"
        )
    count, size = 0, (0, 0)
    for count, frame in enumerate(view.frames(), start=1):
        if count > 1 and frame.shape[:2] != size:
            raise SchemaError(
                f"{view.images()[count - 1]}: image is {frame.shape[1]}x{frame.shape[0]}, the "
                f"camera's earlier frames {size[1]}x{size[0]}; every frame of a camera has one size"
            )
        size = frame.shape[:2]
    if view.is_video:
        check_fully_decoded(view.path, count)
    return count, size


def _validate_sequence(
    src: Path, seq: str, cameras: list[Camera], calibration: str, dataset: DictConfig, default_frame_rate: float
) -> tuple[SequenceInfo, np.ndarray | None]:
    """The sequence's record in the capture and the source frames (T,) it imports (``dataset.start_frame``,
    ``frame_step``, ``max_frames``), None when that is every frame."""
    on_disk = view_sources(src / seq)
    videos_dir = next(iter(on_disk.values())).path.parent if on_disk else src / seq / "videos"
    ids = {c.camera_id for c in cameras}
    without_video, without_camera = sorted(ids - set(on_disk)), sorted(set(on_disk) - ids)
    if without_video:
        cam_id = without_video[0]
        remove = "the camera's row" if calibration.endswith(".parquet") else "the camera's images from the calibration"
        images = (src / seq / "images").is_dir()
        expected = src / seq / "images" / cam_id if images else video_path(src, seq, cam_id)
        noun = "image folder" if images else "video"
        raise SchemaError(
            f"{expected}: camera '{cam_id}' in {calibration} has no {noun} ({noun}s here: "
            f"{sorted(on_disk)}); add the {noun} or remove {remove}"
        )
    if without_camera:
        cam_id = without_camera[0]
        noun = "video" if on_disk[cam_id].is_video else "image folder"
        raise SchemaError(
            f"{on_disk[cam_id].path}: {noun} has no camera '{cam_id}' in {calibration} (cameras: "
            f"{sorted(ids)}); add its calibration or remove the {noun}"
        )
    counts: dict[str, int] = {}
    for cam in cameras:
        path = on_disk[cam.camera_id].path
        counts[cam.camera_id], (height, width) = _scan(on_disk[cam.camera_id])
        if (height, width) != (cam.height, cam.width):
            raise SchemaError(
                f"{path}: frames are {width}x{height} but {calibration} says "
                f"{cam.width}x{cam.height}; fix the calibration or the video"
            )
    if len(set(counts.values())) != 1:
        raise SchemaError(
            f"{videos_dir}: views disagree on frame count {counts}; trim the views to the same synchronised range"
        )
    length = next(iter(counts.values()))
    frames = selected_frames(length, dataset, str(videos_dir))
    has_masks = (src / seq / "masks").is_dir()
    if has_masks:
        for cam in cameras:
            for t in frames:
                mask = read_png(mask_path(src, seq, cam.camera_id, int(t)), 1)
                if mask.shape != (cam.height, cam.width):
                    raise SchemaError(
                        f"{mask_path(src, seq, cam.camera_id, int(t))}: mask is {mask.shape[::-1]}, "
                        f"expected {cam.width}x{cam.height}"
                    )
    fps = (on_disk[cameras[0].camera_id].frame_rate() or float(default_frame_rate)) / int(dataset.get("frame_step", 1))
    info = SequenceInfo(
        num_frames=len(frames),
        frame_rate=fps,
        width=cameras[0].width,
        height=cameras[0].height,
        has_masks=has_masks,
        has_ground_truth=False,
    )
    return info, None if np.array_equal(frames, np.arange(length)) else frames
