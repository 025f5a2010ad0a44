"""``gaussians.parquet``: mesh-bound Gaussians, and ``train_log.parquet``: a training loss curve.

Gaussians are stored in their parent triangle's local frame (GaussianAvatars):
``local_means`` and ``log_scales`` in units of the frame scale k, ``quats``
(w, x, y, z) relative to the frame, ``opacity_logits``, degree-0 SH colour
``sh_dc``; ``binding`` indexes the concatenated faces of the meshes in the order
face, hand, and ``part`` names the mesh.
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

BOUND_GAUSSIANS = TableSchema(
    name="bound_gaussians",
    version=1,
    columns=(
        Column("binding", "int64", doc="parent triangle in the concatenated face list"),
        Column("part", "string", doc="'face' or 'hand'"),
        Column("local_means", "vec_f32", 3, unit="k", doc="position in the parent frame"),
        Column("log_scales", "vec_f32", 3, unit="log k"),
        Column("quats", "vec_f32", 4, doc="w, x, y, z relative to the parent frame"),
        Column("opacity_logits", "float32"),
        Column("sh_dc", "vec_f32", 3, doc="degree-0 SH colour; rgb = 0.5 + 0.2820948 * sh_dc"),
    ),
)

#: The loss terms both training stages log.
_LOSS_COLUMNS = (
    Column("step", "int32"),
    Column("loss", "float32"),
    Column("l1", "float32"),
    Column("dssim", "float32"),
    Column("scale_reg", "float32"),
    Column("position_reg", "float32"),
)

TRAIN_LOG = TableSchema(
    name="train_log",
    version=1,
    columns=(*_LOSS_COLUMNS, Column("num_gaussians", "int32")),
)

DYNAMIC_TRAIN_LOG = TableSchema(
    name="dynamic_train_log",
    version=1,
    columns=(
        *_LOSS_COLUMNS,
        Column("patch", "float32", doc="L_patch: LPIPS-VGG over the hand box and the hand-face overlap"),
        Column("interaction_evaluations", "int32", doc="Gaussians that went through the interaction MLPs"),
    ),
)
