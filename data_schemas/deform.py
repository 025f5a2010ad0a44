"""``deform.parquet``: per-frame per-vertex face offsets caused by contact.

``offsets`` holds V x (dx, dy, dz) in metres (world frame), added to the posed
face mesh; ``contact`` marks frames where the hand touches the face.

``contacts.parquet`` (datasets that ship them, e.g. DECAF): which face and hand
mesh vertices touch the other part in each frame, 1.0 or 0.0 per vertex.
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

CONTACTS = TableSchema(
    name="contacts",
    version=1,
    columns=(
        Column("frame", "int32"),
        Column("contact", "bool", doc="any face vertex in contact"),
        Column("face", "vec_f32", doc="per face-mesh vertex: 1 in contact, 0 not"),
        Column("hand", "vec_f32", doc="per hand-mesh vertex: 1 in contact, 0 not"),
    ),
)
