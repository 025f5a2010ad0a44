"""Per-camera videos (``videos/<camera_id>.mp4``), written and decoded with OpenCV.

Frames are ``(T, H, W, 3)`` uint8 RGB in memory (OpenCV's BGR stays inside this
module). MPEG-4 Part 2 (``mp4v``) is lossy, like a real studio's recordings.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np

from data_schemas.tables import SchemaError
from data_schemas.writes import write_failed

FOURCC = "mp4v"


def write_video(path: str | Path, frames: np.ndarray, fps: float) -> None:
    """Encode ``frames`` (T, H, W, 3) uint8 RGB at ``fps`` frames per second."""
    path = Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise SchemaError(f"{path}: expected (T, H, W, 3) uint8 frames, got {frames.shape} {frames.dtype}")
    write_video_stream(path, frames, fps)


def write_video_stream(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Encode (H, W, 3) uint8 RGB frames one at a time (long videos never sit in memory);
    returns how many were written. Every frame must have the first one's size."""
    path = Path(path)
    if fps <= 0 or not np.isfinite(fps):
        raise SchemaError(f"{path}: frame rate must be positive, got {fps}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer, size, count = None, None, 0
    try:
        for frame in frames:
            frame = checked_frame(path, frame, count, size)
            if writer is None:
                size = frame.shape[:2]
                # ignore: OpenCV's stubs lack the module-level VideoWriter_fourcc (VideoWriter.fourcc is the same
                # function, but tests replace cv2.VideoWriter)
                fourcc = cv2.VideoWriter_fourcc(*FOURCC)  # type: ignore[attr-defined]
                writer = cv2.VideoWriter(str(path), fourcc, float(fps), (size[1], size[0]))
                if not writer.isOpened():
                    raise SchemaError(f"{path}: OpenCV cannot open a {FOURCC} writer (is the directory writable?)")
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
            count += 1
    finally:
        if writer is not None:
            writer.release()
    if count == 0:
        raise SchemaError(f"{path}: no frames to write")
    _check_written(path, count)
    return count


def checked_frame(path: Path, frame: np.ndarray, index: int, size: tuple[int, int] | None) -> np.ndarray:
    """``frame`` as an array if it is (H, W, 3) uint8 RGB of the first frame's ``size`` (None: any), else
    one error naming the video ``path`` and the frame ``index``."""
    frame = np.asarray(frame)
    if (
        frame.ndim != 3
        or frame.shape[-1] != 3
        or frame.dtype != np.uint8
        or (size is not None and frame.shape[:2] != size)
    ):
        raise SchemaError(
            f"{path}: frame {index} is {frame.shape} {frame.dtype}; expected "
            f"{size or '(H, W)'} x 3 uint8 like the first frame"
        )
    return frame


def _check_written(path: Path, count: int) -> None:
    """Reopen a video just written: the container must announce ``count`` frames and the first must
    decode (OpenCV's writer reports success on a full disk, leaving a file without its index)."""
    cap = cv2.VideoCapture(str(path))
    try:
        announced = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0) if cap.isOpened() else 0
        decodes = cap.isOpened() and cap.read()[0]
    finally:
        cap.release()
    if announced != count or not decodes:
        raise write_failed(
            path,
            f"video ({count} frames encoded, {announced} in the file, "
            f"{'first decodes' if decodes else 'none decodes'})",
        )


def read_video(path: str | Path) -> np.ndarray:
    """Decode every frame of a video to (T, H, W, 3) uint8 RGB; one clear error if unreadable."""
    return np.ascontiguousarray(np.stack(list(iter_video(path))))


def iter_video(path: str | Path) -> Iterator[np.ndarray]:
    """Decode a video frame by frame as (H, W, 3) uint8 RGB; one clear error if it is missing or has
    no decodable frame."""
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: video missing; every camera in cameras.parquet needs videos/<camera_id>.mp4")
    cap = cv2.VideoCapture(str(path))
    count = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            count += 1
            yield np.ascontiguousarray(frame[..., ::-1])
    finally:
        cap.release()
    if count == 0:
        raise SchemaError(f"{path}: no decodable frames (corrupt or not a video); re-export it as mp4")


def video_frame_count(path: str | Path) -> int:
    """Frames the container says it holds (fast, no decoding; 0 if unknown or unreadable)."""
    cap = cv2.VideoCapture(str(path))
    try:
        return max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)
    finally:
        cap.release()


def check_fully_decoded(path: str | Path, decoded: int) -> None:
    """Raise if fewer frames decoded than the container announces: the file is damaged (a corrupt or
    truncated stretch stops the decoder), which is not the same fault as views of unequal length."""
    announced = video_frame_count(path)
    if announced and decoded < announced:
        raise SchemaError(
            f"{path}: the file is damaged: only {decoded} of the {announced} frames its container "
            f"announces decode (corrupt or truncated data); re-export or re-encode it, e.g. "
            f"ffmpeg -i <original> -c:v libx264 -pix_fmt yuv420p {Path(path).name}"
        )


def video_fps(path: str | Path) -> float:
    """Frame rate stored in the container (0 if unknown)."""
    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
