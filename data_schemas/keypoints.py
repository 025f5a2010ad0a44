"""``keypoints.parquet``: 2D keypoints per frame, camera and part.

``uvc`` holds K triples (u, v, confidence) flattened; u, v in pixels of the full
camera image (OpenCV convention), confidence in [0, 1], 0 for a keypoint that is
missing or occluded. Hand: 21 keypoints (wrist, then thumb, index, middle, ring,
pinky, four each, tip last); face: the template's landmark set.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

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
