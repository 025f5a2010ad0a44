"""Per-camera videos (``videos/<camera_id>.mp4``), written and decoded with OpenCV.

Frames are ``(T, H, W, 3)`` uint8 RGB in memory (OpenCV's BGR stays inside this
module). MPEG-4 Part 2 (``mp4v``) is lossy, like a real studio's recordings.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from data_schemas.tables import SchemaError

FOURCC = "mp4v"


def write_video(path: str | Path, frames: np.ndarray, fps: float) -> None:
    """Encode ``frames`` (T, H, W, 3) uint8 RGB at ``fps`` frames per second."""
    path = Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise SchemaError(f"{path}: expected (T, H, W, 3) uint8 frames, got {frames.shape} {frames.dtype}")
    if fps <= 0 or not np.isfinite(fps):
        raise SchemaError(f"{path}: frame rate must be positive, got {fps}")
    height, width = frames.shape[1:3]
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*FOURCC), float(fps), (width, height))
    if not writer.isOpened():
        raise SchemaError(f"{path}: OpenCV cannot open a {FOURCC} writer (is the directory writable?)")
    try:
        for frame in frames:
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
    finally:
        writer.release()


def read_video(path: str | Path) -> np.ndarray:
    """Decode every frame of a video to (T, H, W, 3) uint8 RGB; one clear error if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: video missing; every camera in cameras.parquet needs videos/<camera_id>.mp4")
    cap = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame[..., ::-1])
    finally:
        cap.release()
    if not frames:
        raise SchemaError(f"{path}: no decodable frames (corrupt or not a video); re-export it as mp4")
    return np.ascontiguousarray(np.stack(frames))


def video_fps(path: str | Path) -> float:
    """Frame rate stored in the container (0 if unknown)."""
    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
