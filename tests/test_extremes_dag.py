"""The whole DAG at the extremes of a capture: no hand in any view, a single frame per sequence, a single
training camera besides the held-out one. Every stage runs, every number it reports is finite, and the
held-out images are measured (NaN only for a region absent from every image, e.g. the hand of a face-only
capture)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from data_schemas.metrics import METRICS
from data_schemas.tables import read_table
from pipeline.cli import run_app
from stages import REGISTRY
from tests.conftest import compose_cfg

SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "fit.source=ground_truth",
    "run.progress=false",
    "stage.capture.cross_reenactment=false",
]


def _numbers(value: object) -> list[float]:
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return []
    if isinstance(value, (int, float)):
        return [float(value)]
    if isinstance(value, dict):
        return [x for v in value.values() for x in _numbers(v)]
    return [x for v in value for x in _numbers(v)] if isinstance(value, list) else []


def assert_every_metric_finite(subject: Path) -> None:
    """Every stage of ``subject`` (method interactavatar) has a manifest whose numbers are all finite."""
    for s in REGISTRY:
        folder = subject / "methods" / "interactavatar" / s.name if s.per_method else subject / s.name
        metrics = json.loads((folder / "_manifest.json").read_text())["metrics"]
        assert all(math.isfinite(x) for x in _numbers(metrics)), (s.name, metrics)


@pytest.mark.parametrize(
    "extreme",
    [
        ["dataset.scene=face_only"],
        ["quality.num_frames_train=1", "quality.num_frames_test=1"],
        ["stage.capture.num_cameras=2"],
    ],
    ids=["no-hand-in-view", "single-frame", "single-train-camera"],
)
def test_the_whole_dag_runs_and_every_number_is_finite(tmp_path: Path, extreme: list[str]) -> None:
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, *extreme]))
    subject = tmp_path / "synth_a"
    assert_every_metric_finite(subject)
    table = read_table(subject / "methods" / "interactavatar" / "evaluate" / "metrics.parquet", METRICS)
    full = np.asarray(table["region"]) == "full"
    assert full.any() and np.isfinite(np.asarray(table["psnr"])[full]).all()
    hand = np.asarray(table["region"]) == "hand"
    if "dataset.scene=face_only" in extreme:  # no hand pixel anywhere: its region is NaN, not a number
        assert np.isnan(np.asarray(table["psnr"])[hand]).all()
    assert (subject / "methods" / "interactavatar" / "report" / "report.html").is_file()
