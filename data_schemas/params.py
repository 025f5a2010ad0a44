"""``params.parquet``: FLAME and MANO parameters per frame (ground truth, provided or fitted).

Axis-angle rotations in radians, translations in metres. Shape and expression
widths are chosen by the writer (procedural templates: 10; official FLAME: up to
300/100) and uniform within a file.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

PARAMS = TableSchema(
    name="params",
    version=1,
    columns=(
        Column("frame", "int32", doc="frame index in the sequence"),
        Column("flame_shape", "vec_f32", doc="FLAME identity coefficients"),
        Column("flame_expression", "vec_f32", doc="FLAME expression coefficients"),
        Column("flame_global_orient", "vec_f32", 3, unit="rad"),
        Column("flame_neck_pose", "vec_f32", 3, unit="rad"),
        Column("flame_jaw_pose", "vec_f32", 3, unit="rad"),
        Column("flame_eye_pose", "vec_f32", 6, unit="rad", doc="left then right eye"),
        Column("flame_transl", "vec_f32", 3, unit="m"),
        Column("mano_shape", "vec_f32", doc="MANO shape coefficients"),
        Column("mano_hand_pose", "vec_f32", 45, unit="rad", doc="15 finger joints, axis-angle"),
        Column("mano_global_orient", "vec_f32", 3, unit="rad"),
        Column("mano_transl", "vec_f32", 3, unit="m"),
    ),
)
PARAM_COLUMNS = tuple(c.name for c in PARAMS.columns if c.name != "frame")
