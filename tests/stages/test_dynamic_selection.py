"""Stage two's selection wired through the DAG on an 8-frame training motion (issue 40's short capture): the
manifest says what was kept and why, the written model is the kept one, and a selection without withheld warm-up
frames is refused with the fix."""

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
    "stage.warmup.validation.frames=2",
    "stage.dynamic.validation.every=10",
    "stage.dynamic.validation.frames=2",
    "stage.dynamic.select.enabled=true",
]


def _dynamic(out: Path) -> dict:
    return json.loads((out / "synth_a" / "methods" / "interactavatar" / "dynamic" / "_manifest.json").read_text())


def test_the_manifest_and_the_model_say_what_the_selection_kept(tmp_path: Path) -> None:
    run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, *SELECT, "run.until=dynamic"]))
    metrics = _dynamic(tmp_path)["metrics"]
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
    from stages.report import _contact_draws_paragraph, _selection_paragraph  # "What was modelled, and why"

    dynamic_dir = tmp_path / "synth_a" / "methods" / "interactavatar" / "dynamic"
    manifest = json.loads((dynamic_dir / "_manifest.json").read_text())
    draws = _contact_draws_paragraph(manifest)
    assert (f"probability {metrics['contact_draw_probability']:.2f}" in draws) == (metrics["contact_frames"] > 0)
    text = _selection_paragraph(metrics)
    assert f"kept step {metrics['selected_step']} of 20" in text
    assert ("hand MLPs H: kept" in text) == metrics["kept_hand_mlp"]


def test_selection_refuses_a_warmup_that_trained_on_the_validation_frames(tmp_path: Path) -> None:
    cfg = compose_cfg(
        [f"paths.outputs={tmp_path}", *SMALL, *SELECT, "stage.warmup.validation.every=0", "run.until=dynamic"]
    )
    with pytest.raises(Exception, match="stage.warmup.validation.every > 0"):
        run_app(cfg)


def test_selection_without_validation_is_refused_before_work_starts(tmp_path: Path) -> None:
    from pipeline.config import ConfigError

    with pytest.raises(ConfigError, match="select.enabled=true needs validation frames"):
        run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, "stage.dynamic.select.enabled=true"]))
    assert not (tmp_path / "synth_a" / "capture").exists()
