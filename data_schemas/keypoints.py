"""``keypoints.parquet``: 2D keypoints per frame, camera and part.

``uvc`` holds K triples (u, v, confidence) flattened; u, v in pixels of the full
camera image (OpenCV convention), confidence in [0, 1], 0 for a keypoint that is
missing or occluded. Hand: 21 keypoints (wrist, then thumb, index, middle, ring,
pinky, four each, tip last); face: the template's landmark set.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from data_schemas.tables import Column, TableSchema, write_table

KEYPOINTS = TableSchema(
    name="keypoints",
    version=1,
    columns=(
        Column("frame", "int32"),
        Column("camera_id", "string"),
        Column("part", "string", doc="'hand' or 'face'"),
        Column("uvc", "list_f32", unit="px", doc="K x (u, v, confidence), flattened"),
    ),
)
PARTS = ("hand", "face")


def write_keypoints(path: Path, keypoints: Mapping[str, Mapping[str, np.ndarray]], num_frames: int) -> None:
    """Write camera id -> part -> (T, K, 3) (u, v, confidence) arrays as one row per frame, camera and part."""
    rows: dict[str, list] = {"frame": [], "camera_id": [], "part": [], "uvc": []}
    for cam, parts in keypoints.items():
        for part, kp in parts.items():
            for t in range(num_frames):
                rows["frame"].append(t)
                rows["camera_id"].append(cam)
                rows["part"].append(part)
                rows["uvc"].append(kp[t])
    write_table(path, KEYPOINTS, {**rows, "frame": np.array(rows["frame"], dtype=np.int32)})
