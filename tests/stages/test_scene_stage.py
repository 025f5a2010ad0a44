"""The scene stage on the three synthetic scenes: its decisions, and that the stages after it skip what
it leaves out (nothing simulated, no hand Gaussians, no interaction-MLP evaluations)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from data_schemas.deform import DEFORM
from data_schemas.gaussians import BOUND_GAUSSIANS
from data_schemas.scene import SCENE_FRAMES
from data_schemas.tables import read_table
from pipeline.cli import run_app
from tests.conftest import compose_cfg

SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "stage.capture.num_cameras=3",
    "fit.source=ground_truth",
    "run.progress=false",
    "stage.capture.cross_reenactment=false",
]


def _run(out: Path, *extra: str, until: str = "pbd") -> dict:
    """Run the DAG up to ``until``; scene.json."""
    run_app(compose_cfg([f"paths.outputs={out}", *SMALL, f"run.until={until}", *extra]))
    return json.loads((out / "synth_a" / "scene" / "scene.json").read_text())


def _manifest(out: Path, stage: str) -> dict:
    root = out / "synth_a"
    path = root / stage if stage in ("scene", "pbd") else root / "methods" / "interactavatar" / stage
    return json.loads((path / "_manifest.json").read_text())


def test_a_scene_with_contact_models_everything_and_covers_the_true_contacts(tmp_path: Path) -> None:
    scene = _run(tmp_path)
    assert scene["model_hand"] and scene["model_pbd"] and scene["model_interaction"], scene["reasons"]
    frames = read_table(tmp_path / "synth_a" / "scene" / "scene.parquet", SCENE_FRAMES)
    train = np.asarray(frames["sequence"]) == "train"
    deform = read_table(tmp_path / "synth_a" / "capture" / "train" / "gt" / "deform.parquet", DEFORM)
    truth = np.asarray(deform["contact"])
    assert truth.any() and np.asarray(frames["contact"])[train][truth].all()  # every dent is within d_max
    assert 0 < len(scene["deforming_triangles"]) < scene["face_triangles"]
    assert _manifest(tmp_path, "pbd")["metrics"]["simulated_frames"] > 0


def test_no_contact_skips_pbd_and_the_interaction_module(tmp_path: Path) -> None:
    scene = _run(tmp_path, "dataset.scene=no_contact")
    assert scene["model_hand"] and not scene["model_pbd"] and not scene["model_interaction"]
    assert "never comes within d_max" in scene["why"]["model_pbd"]
    assert scene["sequences"]["train"]["closest_mm"] > 50 and not scene["deforming_triangles"]
    report = json.loads((tmp_path / "synth_a" / "pbd" / "pbd_report.json").read_text())
    assert _manifest(tmp_path, "pbd")["metrics"]["simulated_frames"] == 0 and "scene analysis" in report["skipped"]
    offsets = read_table(tmp_path / "synth_a" / "pbd" / "train" / "deform.parquet", DEFORM)["offsets"]
    assert not np.any(offsets)


def test_the_config_overrides_a_decision_and_the_reason_says_so(tmp_path: Path) -> None:
    scene = _run(tmp_path, "stage.scene.model_pbd=false", "quality.num_frames_train=1")  # one frame: still decides
    assert scene["model_hand"] and not scene["model_pbd"] and scene["sequences"]["train"]["frames"] == 1
    assert "set in the config (stage.scene.model_pbd)" in scene["why"]["model_pbd"]
    assert _manifest(tmp_path, "pbd")["metrics"]["simulated_frames"] == 0


@pytest.mark.parametrize("bad", ["maybe", "2"])
def test_a_bad_override_is_one_clear_error(tmp_path: Path, bad: str) -> None:
    with pytest.raises(Exception, match="choose auto, true or false"):
        _run(tmp_path, f"stage.scene.model_hand={bad}")
    assert not (tmp_path / "synth_a" / "scene").exists()


def test_a_face_only_scene_trains_a_face_only_avatar(tmp_path: Path) -> None:
    """No hand in view: no MANO Gaussians, no hand MLPs, nothing simulated, no interaction evaluations."""
    scene = _run(tmp_path, "dataset.scene=face_only", until="dynamic")
    assert not (scene["model_hand"] or scene["model_pbd"] or scene["model_interaction"])
    assert scene["sequences"]["train"]["hand_frames"] == 0 and "face-only" in scene["why"]["model_hand"]
    assert _manifest(tmp_path, "pbd")["metrics"]["simulated_frames"] == 0
    root = tmp_path / "synth_a" / "methods" / "interactavatar"
    for stage in ("warmup", "dynamic"):
        parts = set(read_table(root / stage / "gaussians.parquet", BOUND_GAUSSIANS)["part"])
        assert parts == {"face"}, (stage, parts)
    architecture = json.loads((root / "dynamic" / "model.json").read_text())["architecture"]
    assert not architecture["hand_mlp"] and not architecture["interaction"]
    assert _manifest(tmp_path, "dynamic")["metrics"]["interaction_mlp_evaluations"] == 0
