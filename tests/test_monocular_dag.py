"""The whole DAG on a monocular capture (``dataset.train_cameras=[cam04]``): one training camera, every other
camera held out. The fit runs from one view (templates' sizes for depth), the scene analysis still sees the
hand, and the avatar is measured on the seven cameras it never saw."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from avatar.training.avatar_tracking import untracked_reason
from data_schemas.cameras import read_cameras
from data_schemas.metrics import METRICS, TRACKED_SPLIT
from data_schemas.tables import read_table
from pipeline.cli import run_app
from pipeline.config import ConfigError, validate_config
from stages import REGISTRY
from tests.conftest import compose_cfg
from tests.test_extremes_dag import assert_every_metric_finite


def test_monocular_capture_runs_the_whole_dag(tmp_path: Path) -> None:
    run_app(
        compose_cfg(
            [
                f"paths.outputs={tmp_path}",
                "quality=smoke",
                "run.progress=false",
                "stage.capture.cross_reenactment=false",
                "dataset.train_cameras=[cam04]",
                "stage.evaluate.test_tracking=avatar",  # one camera cannot tune and score: that split is skipped
            ]
        )
    )
    subject = tmp_path / "synth_a"
    cameras = read_cameras(subject / "capture" / "cameras.parquet")
    assert [c.camera_id for c in cameras if c.split == "train"] == ["cam04"] and len(cameras) == 8
    fit = json.loads((subject / "fit" / "fit_report.json").read_text())
    assert fit["source"] == "fitted" and fit["train_views"] == 1
    train = fit["sequences"]["train"]
    assert train["reprojection_px"]["face"] < 3.0  # the one view is explained ...
    # ... but depth is only known through size: the error lies along the camera's axis (docs/how-to/monocular-video.md
    # video": about 50 mm for the face here, against 1.1 mm from eight views).
    assert train["mpjpe_face_mm"] < 150.0
    scene = json.loads((subject / "scene" / "scene.json").read_text())
    assert scene["model_hand"] and scene["thresholds"]["min_views"] == 1
    assert_every_metric_finite(subject)
    table = read_table(subject / "methods" / "interactavatar" / "evaluate" / "metrics.parquet", METRICS)
    novel = np.asarray(table["split"]) == "novel_view"
    assert set(np.asarray(table["camera_id"])[novel]) == {f"cam{i:02d}" for i in range(8) if i != 4}
    assert np.isfinite(np.asarray(table["psnr"])[novel & (np.asarray(table["region"]) == "full")]).all()
    evaluate = json.loads((subject / "methods" / "interactavatar" / "evaluate" / "_manifest.json").read_text())
    assert evaluate["metrics"][f"{TRACKED_SPLIT}_skipped"] == untracked_reason(["cam04"])
    assert TRACKED_SPLIT not in set(table["split"])


@pytest.mark.parametrize("tuning", ["auto", "[cam04]"])
def test_a_monocular_capture_with_the_avatar_tracking_is_planned_without_its_split(tuning: str) -> None:
    """One training camera cannot both tune the held-out motion's frames and score them: the config check refuses
    nothing (it asked to "name fewer" tuning cameras than the one there is), and evaluate skips the split saying why,
    as it skips the novel view of a capture without a held-out camera."""
    cfg = compose_cfg(
        [
            "dataset.train_cameras=[cam04]",
            "stage.evaluate.test_tracking=avatar",
            f"stage.evaluate.tuning_cameras={tuning}",
        ]
    )
    validate_config(cfg, REGISTRY)
    reason = untracked_reason(["cam04"])
    assert reason is not None and "one training camera (cam04)" in reason and "name fewer" not in reason
    assert untracked_reason(["cam00", "cam04"]) is None


def test_train_cameras_naming_no_camera_is_one_clear_error(tmp_path: Path) -> None:
    for bad in ("[cam99]", "[cam00,cam01,cam02,cam03,cam04,cam05,cam06,cam07]"):
        with pytest.raises(
            ConfigError,
            match=r"dataset.train_cameras=\[.*\]: choose some but not all of the synthetic "
            r"rig's cameras",
        ):  # refused before the capture is generated
            run_app(
                compose_cfg(
                    [
                        f"paths.outputs={tmp_path}",
                        "quality=smoke",
                        "quality.capture_size=32",
                        "run.progress=false",
                        "run.until=capture",
                        "stage.capture.cross_reenactment=false",
                        f"dataset.train_cameras={bad}",
                    ]
                )
            )
        assert not (tmp_path / "synth_a" / "capture").exists()
