"""``scene.parquet``: what every frame of every sequence shows (stage ``scene``); ``scene.json`` holds the
decisions taken from it (docs/explanation/scene.md)."""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

SCENE_FRAMES = TableSchema(
    name="scene_frames",
    version=1,
    columns=(
        Column("sequence", "string"),
        Column("frame", "int32"),
        Column("hand_views", "int32", doc="training cameras in which the hand covers at least min_hand_area"),
        Column("hand_present", "bool", doc="hand_views >= min_views"),
        Column(
            "distance_m",
            "float64",
            unit="m",
            finite=False,
            doc="smallest face-vertex-to-hand distance; NaN where the hand is not present",
        ),
        Column("contact", "bool", doc="hand present and within d_max of the face"),
        Column("near_vertices", "int32", doc="face vertices within d_max of the hand (contact frames)"),
    ),
)
