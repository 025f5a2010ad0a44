"""The ``frames`` artifact: per-view square crops, part masks and boxes, ready for the avatar.

Layout::

    index.parquet                                   one row per (sequence, camera, frame)
    <sequence>/<camera_id>/rgb/<frame:06d>.png      crop, (S, S, 3) uint8 sRGB
    <sequence>/<camera_id>/mask/<frame:06d>.png     crop labels (S, S) uint8: 0 bg, 1 face, 2 hand,
                                                    3 foreground of unknown part (keyed masks),
                                                    4 unobserved (the crop reaches past the camera image)

The crop of a view is fixed over a sequence; ``K`` is the crop's intrinsics
(OpenCV pixel convention), ``crop`` the window (x0, y0, size) in the full image.
Boxes are (x0, y0, x1, y1) in crop pixels, zero when the part is not visible.
Where a crop reaches past the camera image its RGB is padded with the background
colour and its label is ``UNOBSERVED``: no camera saw those pixels, so no loss
or metric may compare a render with them.
"""

from __future__ import annotations

from pathlib import Path

from data_schemas.tables import Column, TableSchema

FRAMES_INDEX = TableSchema(
    name="frames_index",
    version=1,
    columns=(
        Column("sequence", "string"),
        Column("camera_id", "string"),
        Column("frame", "int32"),
        Column("split", "string", doc="camera split: 'train' or 'test'"),
        Column("crop", "vec_f64", 3, unit="px", doc="x0, y0, size of the window in the full image"),
        Column("K", "vec_f64", 9, unit="px", doc="crop intrinsics, row-major 3x3"),
        Column("face_box", "vec_f32", 4, unit="px"),
        Column("hand_box", "vec_f32", 4, unit="px"),
        Column("face_visible", "bool"),
        Column("hand_visible", "bool"),
        Column("foreground_fraction", "float32", doc="share of crop pixels that are foreground"),
    ),
)
UNKNOWN_PART = 3
UNOBSERVED = 4  # crop padding outside the camera image


def rgb_path(root: Path, sequence: str, camera_id: str, frame: int) -> Path:
    return root / sequence / camera_id / "rgb" / f"{frame:06d}.png"


def crop_mask_path(root: Path, sequence: str, camera_id: str, frame: int) -> Path:
    return root / sequence / camera_id / "mask" / f"{frame:06d}.png"
