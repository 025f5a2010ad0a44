"""``embedded_gaussians.parquet``: mesh-embedded Gaussians (the SplattingAvatar baseline), and its
training log.

Each Gaussian lies at barycentrics ``(u, v)`` (``w = 1 - u - v``; weights of the triangle's vertices
0, 1, 2) of its ``triangle`` in the concatenated faces of the meshes (order face, hand), lifted by
``displacement`` along the interpolated vertex normal; ``log_scales`` are canonical world scales
(scaled on a posed mesh by the square root of the triangle's area change), ``quats`` (w, x, y, z) its
rotation in the canonical world frame, then ``opacity_logits`` and the degree-0 SH colour ``sh_dc``.
The canonical mesh itself (the first training frame's) is not stored here.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

EMBEDDED_GAUSSIANS = TableSchema(
    name="embedded_gaussians",
    version=1,
    columns=(
        Column("triangle", "int64", doc="face in the concatenated face list"),
        Column("part", "string", doc="'face' or 'hand'"),
        Column("barycentric", "vec_f32", 2, doc="u, v (w = 1 - u - v), inside the triangle"),
        Column("displacement", "float32", unit="m", doc="along the interpolated unit vertex normal"),
        Column("log_scales", "vec_f32", 3, unit="log m", doc="canonical world scale"),
        Column("quats", "vec_f32", 4, doc="w, x, y, z in the canonical world frame"),
        Column("opacity_logits", "float32"),
        Column("sh_dc", "vec_f32", 3, doc="degree-0 SH colour; rgb = 0.5 + 0.2820948 * sh_dc"),
    ),
)

SPLATTING_TRAIN_LOG = TableSchema(
    name="splatting_train_log",
    version=1,
    columns=(
        Column("step", "int32"),
        Column("loss", "float32"),
        Column("l1", "float32"),
        Column("dssim", "float32"),
        Column("mse", "float32"),
        Column("lpips", "float32", doc="LPIPS-AlexNet of the whole crop; 0 when its weight is 0"),
        Column("scale_reg", "float32", doc="mean largest scale of needle-like Gaussians"),
        Column("num_gaussians", "int32"),
        Column("walked", "int32", doc="Gaussians that changed triangle since the previous row"),
    ),
)
