"""``curve.parquet``: image quality during training, on training frames withheld from it (stages ``warmup``
and ``dynamic``; :mod:`avatar.training.validation`).

One row per validation: after ``step`` optimiser steps and ``wall_s`` seconds of training (validation time
excluded; a resumed run counts the time up to its checkpoint), the mean full-image PSNR of the withheld
frames of the training sequence seen from the training cameras (never the held-out camera or motion: those
are the test splits), and their mean LPIPS-alex where the stage measured it (``validation.lpips``; NaN
otherwise). The first row is the starting model, the last the model the stage wrote. No rows
when the stage ran without validation (``validation.every: 0``).
"""

from __future__ import annotations

from data_schemas.tables import Column, TableSchema

CURVE = TableSchema(
    name="curve",
    version=2,
    columns=(
        Column("step", "int32", doc="optimiser steps done"),
        Column("wall_s", "float32", unit="s", doc="training wall time so far, validation excluded"),
        Column(
            "psnr",
            "float32",
            unit="dB",
            finite=False,
            doc="mean per-image PSNR of the withheld frames (+inf where a render equals its ground truth)",
        ),
        Column(
            "lpips",
            "float32",
            finite=False,
            doc="mean LPIPS-alex of the withheld frames (NaN: not measured, validation.lpips off)",
        ),
    ),
)
