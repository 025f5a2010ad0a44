"""``metrics.parquet``: image quality per method, split, camera, frame and region.

``split``: ``novel_view`` (held-out camera, train motion) or ``self_reenact``
(train cameras, held-out test motion). ``region``: ``full``, ``hand``, ``face``,
``interaction`` (the overlap of the hand and face boxes). A metric is NaN where
the region is absent from the ground-truth frame.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

METRICS = TableSchema(
    name="metrics",
    version=1,
    columns=(
        Column("method", "string"),
        Column("split", "string"),
        Column("camera_id", "string"),
        Column("frame", "int32"),
        Column("region", "string"),
        Column("contact", "bool", doc="hand touches the face in this frame (ground truth; False when unknown)"),
        Column("psnr", "float32", unit="dB", finite=False),
        Column("ssim", "float32", finite=False),
        Column("lpips", "float32", finite=False),
    ),
)
SPLITS = ("novel_view", "self_reenact")
REGIONS = ("full", "hand", "face", "interaction")
