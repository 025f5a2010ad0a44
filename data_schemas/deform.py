"""``deform.parquet``: per-frame per-vertex face offsets caused by contact.

``offsets`` holds V x (dx, dy, dz) in metres (world frame), added to the posed
face mesh; ``contact`` marks frames where the hand touches the face.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

DEFORM = TableSchema(
    name="deform",
    version=1,
    columns=(
        Column("frame", "int32"),
        Column("contact", "bool"),
        Column("offsets", "vec_f32", unit="m", doc="V x 3 per-vertex displacement, flattened"),
    ),
)
