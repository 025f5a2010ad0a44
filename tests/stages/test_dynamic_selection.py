"""Stage two's selection wired through the DAG on an 8-frame training motion (issue 40's short capture): the
manifest says what was kept and why, the written model is the kept one (retrained on every frame with exactly the
chosen steps and modules, issue 53), a capture too short to withhold anything trains on all of it and says so, and a
selection without withheld warm-up frames is refused with the fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.cli import run_app
from tests.conftest import compose_cfg

SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "stage.capture.num_cameras=3",
    "fit.source=ground_truth",
    "run.progress=false",
    "stage.capture.cross_reenactment=false",
    "quality.warmup_steps=40",
    "quality.dynamic_steps=20",
    "quality.num_frames_train=8",
]
SELECT = [
    "stage.warmup.validation.every=20",
    "stage.warmup.validation.fraction=0.25",
    "stage.dynamic.validation.every=10",
    "stage.dynamic.validation.fraction=0.25",
    "stage.dynamic.select.enabled=true",
]


def _manifest(out: Path, stage: str) -> dict:
    return json.loads((out / "synth_a" / "methods" / "interactavatar" / stage / "_manifest.json").read_text())


def _dynamic(out: Path) -> dict:
    return _manifest(out, "dynamic")


def test_choosing_then_retraining_uses_exactly_the_chosen_steps_and_modules_on_every_frame(tmp_path: Path) -> None:
    """The validated runs (two restarts) withhold 2 of 8 frames and choose; the model written trains on all 8 from the
    warm-up's own retrain, for the chosen step and with the kept modules only."""
    run_app(
        compose_cfg([f"paths.outputs={tmp_path}", *SMALL, *SELECT, "stage.dynamic.restarts=2", "run.until=dynamic"])
    )
    warmup = _manifest(tmp_path, "warmup")["metrics"]
    assert warmup["validation_frames_withheld"] == 2 and warmup["final_training_frames"] == 8
    warmup_dir = tmp_path / "synth_a" / "methods" / "interactavatar" / "warmup"
    assert (warmup_dir / "validation" / "gaussians.parquet").is_file()
    assert (warmup_dir / "validation" / "params.parquet").is_file()
    metrics = _dynamic(tmp_path)["metrics"]
    assert metrics["validation_frames_withheld"] == 2 and metrics["final_training_frames"] == 8
    assert metrics["retrained_on_all_frames"] is True
    assert metrics["steps"] == metrics["selected_step"]  # the retrain ran exactly the chosen steps
    assert metrics["restarts"] == 2 and metrics["selected_seed"] == 1000 * metrics["selected_restart"]
    psnrs = [metrics[f"restart{i}_selection_psnr"] for i in range(2)]
    assert metrics["selection_psnr"] == max(psnrs)
    model = json.loads((tmp_path / "synth_a" / "methods" / "interactavatar" / "dynamic" / "model.json").read_text())
    assert model["retrained_on_all_frames"] is True
    assert model["architecture"]["hand_mlp"] == metrics["kept_hand_mlp"]  # a module not kept is not even built
    assert model["architecture"]["interaction"] == metrics["kept_interaction"]
    from reporting.training import withheld_paragraph

    assert "withheld 2 of 8 training frames" in withheld_paragraph(_dynamic(tmp_path))
    # the warm-up's retrain is the warm-up without validation, bit for bit: the same seed, steps and frames
    plain = tmp_path / "plain"
    run_app(compose_cfg([f"paths.outputs={plain}", *SMALL, "run.until=warmup"]))
    plain_dir = plain / "synth_a" / "methods" / "interactavatar" / "warmup"
    for name in ("gaussians.parquet", "params.parquet", "gaussians.ply"):
        assert (warmup_dir / name).read_bytes() == (plain_dir / name).read_bytes(), name


def test_a_capture_too_short_to_withhold_a_frame_trains_on_all_of_it_and_says_so(tmp_path: Path) -> None:
    overrides = [*SMALL, *SELECT, "quality.num_frames_train=4", "run.until=dynamic"]
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *overrides]))
    for stage in ("warmup", "dynamic"):
        metrics = _manifest(tmp_path, stage)["metrics"]
        assert metrics["validation_frames_withheld"] == 0 and metrics["final_training_frames"] == 4, stage
    metrics = _dynamic(tmp_path)["metrics"]
    assert "selected_step" not in metrics and metrics["steps"] == 20
    from reporting.training import withheld_paragraph

    text = withheld_paragraph(_dynamic(tmp_path))
    assert "Nothing could be withheld for validation: with 4 training frames, at least 4 must stay" in text


def test_the_manifest_and_the_model_say_what_the_selection_kept(tmp_path: Path) -> None:
    """Without the retrain (today's protocol before issue 53) the model written is the validated run's."""
    overrides = [*SMALL, *SELECT, "stage.warmup.validation.retrain=false", "stage.dynamic.validation.retrain=false"]
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *overrides, "run.until=dynamic"]))
    metrics = _dynamic(tmp_path)["metrics"]
    assert metrics["validation_frames_withheld"] == 2 and metrics["final_training_frames"] == 6
    assert metrics["retrained_on_all_frames"] is False
    assert not (tmp_path / "synth_a" / "methods" / "interactavatar" / "warmup" / "validation").exists()
    assert metrics["selected_step"] in (0, 10, 20) and metrics["selection_final_step"] == 20
    assert isinstance(metrics["kept_hand_mlp"], bool) and isinstance(metrics["kept_interaction"], bool)
    assert metrics["selection_selected_psnr"] >= metrics["selection_final_psnr"]
    for module in ("hand_mlp", "interaction"):  # each is switched off exactly when it is worth <= the margin
        worth = metrics["selection_selected_psnr"] - metrics[f"selection_psnr_without_{module}"]
        if module == "interaction" and not metrics["kept_hand_mlp"]:
            worth = metrics["selection_psnr_without_hand_mlp"] - metrics[f"selection_psnr_without_{module}"]
        assert metrics[f"kept_{module}"] == (worth > 0.05)
    model = json.loads((tmp_path / "synth_a" / "methods" / "interactavatar" / "dynamic" / "model.json").read_text())
    assert model["selection"]["selected_step"] == metrics["selected_step"]
    capture = json.loads((tmp_path / "synth_a" / "capture" / "_manifest.json").read_text())["metrics"]
    assert capture["train_frames"] == 8
    from reporting.training import contact_draws_paragraph, selection_paragraph  # "What was modelled, and why"

    dynamic_dir = tmp_path / "synth_a" / "methods" / "interactavatar" / "dynamic"
    manifest = json.loads((dynamic_dir / "_manifest.json").read_text())
    draws = contact_draws_paragraph(manifest)
    assert (f"probability {metrics['contact_draw_probability']:.2f}" in draws) == (metrics["contact_frames"] > 0)
    text = selection_paragraph(metrics)
    assert f"kept step {metrics['selected_step']} of 20" in text
    assert ("hand MLPs H: kept" in text) == metrics["kept_hand_mlp"]


@pytest.mark.parametrize("override", ["stage.warmup.validation.every=0", "stage.warmup.validation.fraction=0.5"])
def test_selection_refuses_a_warmup_that_trained_on_the_validation_frames(tmp_path: Path, override: str) -> None:
    from pipeline.config import ConfigError

    cfg = compose_cfg([f"paths.outputs={tmp_path}", *SMALL, *SELECT, override, "run.until=dynamic"])
    with pytest.raises(ConfigError, match="stage.warmup.validation.every > 0"):
        run_app(cfg)
    assert not (tmp_path / "synth_a" / "capture").exists()


def test_selection_without_validation_is_refused_before_work_starts(tmp_path: Path) -> None:
    from pipeline.config import ConfigError

    with pytest.raises(ConfigError, match="select.enabled=true needs validation frames"):
        run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, "stage.dynamic.select.enabled=true"]))
    assert not (tmp_path / "synth_a" / "capture").exists()
