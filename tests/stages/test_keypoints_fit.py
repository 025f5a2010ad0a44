"""keypoints and fit stages on the synthetic capture."""

from __future__ import annotations

import json

import numpy as np

from data_schemas.keypoints import KEYPOINTS
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import read_table
from pipeline.cli import run_app
from tests.conftest import compose_cfg


def test_ground_truth_source_reproduces_the_capture_and_noise_is_applied(tmp_path):
    cfg = compose_cfg([f"paths.outputs={tmp_path}", "quality=smoke", "run.until=fit", "run.progress=false",
                       "fit.source=ground_truth", "stage.keypoints.pixel_noise=2.0", "stage.keypoints.drop_rate=0.2"])
    run_app(cfg)
    root = tmp_path / "synth_a"
    report = json.loads((root / "fit" / "fit_report.json").read_text())
    assert report["source"] == "ground_truth"
    for seq in ("train", "test"):
        assert report["sequences"][seq]["mpjpe_hand_mm"] == 0.0
        fitted = read_table(root / "fit" / seq / "params.parquet", PARAMS)
        gt = read_table(root / "capture" / seq / "gt" / "params.parquet", PARAMS)
        for k in PARAM_COLUMNS:
            np.testing.assert_array_equal(fitted[k], gt[k])
    noisy = read_table(root / "keypoints" / "train" / "keypoints.parquet", KEYPOINTS)
    clean = read_table(root / "capture" / "train" / "gt" / "keypoints.parquet", KEYPOINTS)
    a = np.concatenate([np.reshape(k, (-1, 3)) for k in noisy["uvc"]])
    b = np.concatenate([np.reshape(k, (-1, 3)) for k in clean["uvc"]])
    kept = (a[:, 2] > 0) & (b[:, 2] > 0)
    assert 0.6 < kept.sum() / (b[:, 2] > 0).sum() < 0.95  # about 20% dropped
    err = np.linalg.norm(a[kept, :2] - b[kept, :2], axis=1)
    assert 1.5 < np.sqrt((err**2).mean() / 2) < 2.5  # 2 px per axis
