"""The report's validation section: PSNR always, LPIPS on a second axis only where a stage measured it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from data_schemas.curve import CURVE
from data_schemas.tables import write_table
from reporting.training import validation_section


def _curve(folder: Path, lpips: list[float] | None) -> Path:
    folder.mkdir(parents=True)
    n = 3 if lpips is None else len(lpips)
    write_table(
        folder / "curve.parquet",
        CURVE,
        {
            "step": np.arange(n, dtype=np.int64) * 10,
            "wall_s": np.arange(n, dtype=np.float64),
            "psnr": 25.0 + np.arange(n, dtype=np.float64),
            "lpips": np.array(lpips if lpips is not None else [math.nan] * n, dtype=np.float64),
        },
    )
    return folder


def test_lpips_is_drawn_only_when_a_curve_has_it(tmp_path: Path):
    warmup = _curve(tmp_path / "warmup", None)
    assert "Validation PSNR during" in validation_section(warmup, _curve(tmp_path / "plain", None))
    html = validation_section(warmup, _curve(tmp_path / "dynamic", [0.05, 0.04, 0.035]))
    assert "Validation PSNR and LPIPS during" in html and "data:image/png;base64," in html


def test_no_curve_says_how_to_get_one(tmp_path: Path):
    empty = tmp_path / "none"
    empty.mkdir()
    assert "stage.dynamic.validation.every" in validation_section(empty, empty)
