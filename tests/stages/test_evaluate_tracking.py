"""stage.evaluate.test_tracking=avatar on a small smoke capture: the held-out motion is tracked by the frozen avatar on
the tuning training cameras and scored on the others only; the refinement never sees a view that scores it nor the
held-out camera; both protocols are reported, and the tracked parameters are written."""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from avatar.artifacts import load_ground_truth_params, load_params, read_params
from avatar.artifacts.motion import templates
from avatar.training.avatar_tracking import tracking_cameras
from data_schemas.cameras import read_cameras
from data_schemas.metrics import METRICS, TRACKED_SPLIT
from data_schemas.tables import SchemaError, read_table
from pipeline.cli import run_app
from pipeline.config import ConfigError, validate_config
from reporting.evaluation import held_out_tracking_section
from stages import REGISTRY
from tests.conftest import compose_cfg

#: the module (``stages.evaluate`` is the registered stage of the same name)
EVALUATE = importlib.import_module("stages.evaluate")
SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "stage.capture.num_cameras=5",
    "fit.source=ground_truth",
    "run.progress=false",
    "stage.capture.cross_reenactment=false",
    "quality.warmup_steps=60",
    "quality.dynamic_steps=10",
    "stage.evaluate.tracking.steps=8",
]


def test_the_avatar_tracked_motion_is_scored_only_on_cameras_that_did_not_tune_it(tmp_path: Path, monkeypatch) -> None:
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, "run.until=dynamic"]))
    root = tmp_path / "synth_a"
    cameras = read_cameras(root / "capture" / "cameras.parquet")
    train = sorted(c.camera_id for c in cameras if c.split == "train")
    held_out = [c.camera_id for c in cameras if c.split == "test"]
    assert len(train) == 4 and held_out
    seen: list[list[str]] = []
    track = EVALUATE.track_with_avatar

    def recording_track(pose, params, head, hand, offsets, views, config, *args, **kwargs):
        seen.append(list(views.camera_ids))  # what the refinement was given: every image it can look at
        return track(pose, params, head, hand, offsets, views, config, *args, **kwargs)

    monkeypatch.setattr(EVALUATE, "track_with_avatar", recording_track)
    run_app(
        compose_cfg([f"paths.outputs={tmp_path}", *SMALL, "run.only=evaluate", "stage.evaluate.test_tracking=avatar"])
    )
    evaluate = root / "methods" / "interactavatar" / "evaluate"
    rows = read_table(evaluate / "metrics.parquet", METRICS)
    scored = {s: sorted(set(np.asarray(rows["camera_id"])[np.asarray(rows["split"]) == s])) for s in set(rows["split"])}
    assert seen == [train[::2]], seen  # auto: the 1st and 3rd training camera tune, one call for the held-out motion
    assert scored[TRACKED_SPLIT] == train[1::2]
    assert not set(seen[0]) & set(scored[TRACKED_SPLIT]), "a camera tuned the frames it scores"
    assert not set(seen[0]) & set(held_out), "the refinement saw the held-out camera"
    assert scored["self_reenact"] == train  # the tracker protocol, as before, on every training camera
    metrics = json.loads((evaluate / "_manifest.json").read_text())["metrics"]
    assert metrics["tracking_tuning_cameras"] == ",".join(train[::2])
    assert metrics["tracking_scoring_cameras"] == ",".join(train[1::2])
    assert metrics["tracking_loss_after"] < metrics["tracking_loss_before"], metrics
    for key in (
        "self_reenact_scoring_psnr",
        "self_reenact_tracked_psnr",
        "tracking_moved_hand_mm_mean",
        "tracking_before_mpjpe_hand_mm",  # the capture's ground truth: the fit's error and the refined one
        "tracking_after_vertex_error_face_mm",
    ):
        assert np.isfinite(metrics[key]), key
    tracked, fitted = read_params(evaluate / "tracking" / "test" / "params.parquet"), load_params(root / "fit", "test")
    np.testing.assert_array_equal(tracked["flame_shape"], fitted["flame_shape"])  # the identity stays
    assert not np.array_equal(tracked["flame_transl"], fitted["flame_transl"])  # the frames were refined

    # the report says what was tuned and scored, the errors against the truth, and draws the three meshes
    cfg = compose_cfg([f"paths.outputs={tmp_path}", *SMALL])
    method = root / "methods" / "interactavatar"
    ctx = SimpleNamespace(cfg=cfg, input_dir=lambda name: method / name if name == "evaluate" else root / name)
    manifest = json.loads((evaluate / "_manifest.json").read_text())
    page = held_out_tracking_section(
        ctx, manifest, *templates(cfg.model), lambda s: load_ground_truth_params(root / "capture", s)
    )
    assert f"on the training cameras {', '.join(train[::2])} and scored on the others ({', '.join(train[1::2])}" in page
    assert "face landmarks" in page and "true (blue)" in page and "data:image/png;base64" in page
    num_frames = len(fitted["flame_shape"])
    assert page.count("<tr>") == 1 + 3 + 1 + num_frames  # the 3D errors (header + 3), the frames (header + T)

    # the tracker protocol alone (the default) writes no tracked split and an empty tracking folder
    seen.clear()
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, "run.only=evaluate"]))
    assert not seen and not any((evaluate / "tracking").iterdir())
    assert TRACKED_SPLIT not in set(read_table(evaluate / "metrics.parquet", METRICS)["split"])


def test_tuning_cameras_auto_alternate_and_a_list_names_the_tuning_ones() -> None:
    ids = ["cam04", "cam00", "cam02", "cam01"]
    assert tracking_cameras("auto", ids) == (["cam00", "cam02"], ["cam01", "cam04"])
    assert tracking_cameras(["cam04"], ids) == (["cam04"], ["cam00", "cam01", "cam02"])
    with pytest.raises(SchemaError, match=r"\['cam09'\] are not training cameras"):
        tracking_cameras(["cam09"], ids)
    with pytest.raises(SchemaError, match="leaves no training camera to score"):
        tracking_cameras(ids, ids)
    with pytest.raises(SchemaError, match=r"one training camera \(cam00\): none is left to score .*=tracker$"):
        tracking_cameras("auto", ["cam00"])  # not "name fewer": evaluate skips the split on such a capture


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("stage.evaluate.test_tracking=both", "stage.evaluate.test_tracking=both: choose one of tracker, avatar"),
        ("stage.evaluate.tuning_cameras=[]", "stage.evaluate.tuning_cameras=[]: 'auto' or a non-empty list"),
        ("stage.evaluate.tracking.final_rate=2", "stage.evaluate.tracking.final_rate=2: must be in (0, 1]"),
    ],
)
def test_bad_tracking_settings_are_refused_before_any_stage_runs(override: str, message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        validate_config(compose_cfg([override]), REGISTRY)
    assert message in str(caught.value), str(caught.value)
    assert OmegaConf.select(compose_cfg([]), "stage.evaluate.test_tracking") == "tracker"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        # cam03 is the synthetic rig's held-out camera: this failed in evaluate, after its other splits had rendered
        (["stage.evaluate.tuning_cameras=[cam03]"], "stage.evaluate.tuning_cameras=['cam03']: cam03 held out"),
        (["stage.evaluate.tuning_cameras=[cam00,cam02,cam00]"], "cam00 listed more than once; name each once"),
        (["stage.evaluate.tuning_cameras=[cam09]"], "['cam09'] are not training cameras of this capture"),
        (["dataset.train_cameras=[cam00,cam01]", "stage.evaluate.tuning_cameras=[cam02]"], "cam02 held out"),
        (
            ["dataset.train_cameras=[cam00,cam01]", "stage.evaluate.tuning_cameras=[cam00,cam01]"],
            "leaves no training camera to score",
        ),
    ],
)
def test_tuning_cameras_the_capture_cannot_tune_on_are_refused_before_any_stage_runs(
    overrides: list[str], message: str
) -> None:
    with pytest.raises(ConfigError) as caught:
        validate_config(compose_cfg(["stage.evaluate.test_tracking=avatar", *overrides]), REGISTRY)
    assert len(caught.value.problems) == 1 and message in caught.value.problems[0], caught.value.problems


def test_tuning_cameras_among_the_training_ones_are_accepted() -> None:
    validate_config(
        compose_cfg(["stage.evaluate.test_tracking=avatar", "stage.evaluate.tuning_cameras=[cam00]"]), REGISTRY
    )
