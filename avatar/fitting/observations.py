"""Packing per-camera keypoint dictionaries into dense arrays."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from avatar.fitting.triangulation import clean_observations
from data_schemas.cameras import Camera

PART_SIZES = {"hand": 21, "face": 68}


@dataclass(frozen=True)
class Observations:
    """Detections of one part: uv (T, C, K, 2) px (0 where missing) and conf (T, C, K) in [0, 1]."""

    uv: np.ndarray
    conf: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.uv.shape[0])


def pack_part(
    keypoints: Mapping[str, Mapping[str, np.ndarray]], cameras: Sequence[Camera], part: str, num_points: int
) -> Observations:
    """Stack ``keypoints[camera_id][part]`` (T, K, 3) rows (u, v, conf) over ``cameras``.

    A camera without detections of the part contributes zero confidence;
    NaN entries become zero confidence (see :func:`clean_observations`).
    """
    lengths = {np.asarray(parts[p]).shape[0] for parts in keypoints.values() for p in parts}
    if len(lengths) != 1:
        raise ValueError(f"keypoint arrays disagree on the number of frames: {sorted(lengths)}")
    T = lengths.pop()
    uvc = np.zeros((T, len(cameras), num_points, 3))
    for c, cam in enumerate(cameras):
        arr = keypoints.get(cam.camera_id, {}).get(part)
        if arr is None:
            continue
        arr = np.asarray(arr, np.float64)
        if arr.shape != (T, num_points, 3):
            raise ValueError(f"keypoints[{cam.camera_id!r}][{part!r}] must be ({T}, {num_points}, 3), got {arr.shape}")
        uvc[:, c] = arr
    uv, conf = clean_observations(uvc)
    return Observations(uv, conf)


def keypoints_by_camera(table: dict, num_frames: int) -> dict[str, dict[str, np.ndarray]]:
    """keypoints.parquet rows -> camera_id -> part -> (T, K, 3)."""
    out: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
    for frame, cam, part, uvc in zip(table["frame"], table["camera_id"], table["part"], table["uvc"]):
        rows = np.asarray(uvc, np.float64).reshape(-1, 3)
        if part not in out[cam]:
            out[cam][part] = np.zeros((num_frames, len(rows), 3))
        out[cam][part][int(frame)] = rows
    return dict(out)
