"""A training run whose loss stops being finite (learning rates far too high): one error naming the step and the
learning rates to lower by their config keys, and no checkpoint left that a later run could resume the divergence
from. The stage's error names the stage and its output folder, never the removed temporary folder."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.posing import MeshSequence
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.stage_two import CHECKPOINT as STAGE_TWO_CHECKPOINT
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from avatar.representations.bound.warmup import CHECKPOINT as WARMUP_CHECKPOINT
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.training.checkpoint import previous_path
from avatar.training.loop import TrainingDiverged, advising, learning_rates
from pipeline.cli import run_app
from pipeline.runner import StageFailed
from tests.conftest import compose_cfg
from tests.representations.bound.conftest import make_scene
from tests.training.test_validation import _scene


def _checkpoints(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def _poisoned(meshes: MeshSequence) -> MeshSequence:
    """``meshes`` with every vertex NaN: every loss from the next step on is NaN, as when a run diverges."""
    return MeshSequence(
        torch.full_like(meshes.vertices, float("nan")), meshes.faces, meshes.face_part, meshes.part_names
    )


def test_a_diverged_warmup_raises_at_the_step_and_deletes_its_checkpoints(tmp_path: Path) -> None:
    """A run that saved checkpoints (steps 2 and 4), resumed, diverges: the error names the step the loss was read
    at, and neither checkpoint is left to resume from."""
    views, meshes = _scene(3)

    def train(steps: int, poses: MeshSequence) -> None:
        model = BoundGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 8, init_opacity=0.3)
        cfg = WarmupTrainConfig(steps=steps, log_every=3, checkpoint_every=2, backend="torch")
        train_warmup(model, views, poses, cfg, checkpoint_dir=tmp_path)

    train(4, meshes)
    assert _checkpoints(tmp_path) == [WARMUP_CHECKPOINT, previous_path(tmp_path / WARMUP_CHECKPOINT).name]
    with pytest.raises(TrainingDiverged, match=r"^training diverged at step \d+: the loss is nan$") as caught:
        train(12, _poisoned(meshes))  # resumed at step 4
    assert caught.value.step in (6, 8, 9, 10, 12)  # a step the log or a checkpoint reads
    assert _checkpoints(tmp_path) == []


def test_a_diverged_stage_two_raises_and_deletes_its_checkpoints(tmp_path: Path) -> None:
    scene = make_scene([0.08, 0.3, 0.02])
    cfg = DynamicTrainConfig(steps=2, backend="auto", log_every=4, checkpoint_every=1, patch_weight=0.0)
    contact = np.array([True, False, True])
    train_dynamic(scene.model(), scene.views, scene.meshes, scene.cond, contact, cfg, checkpoint_dir=tmp_path)
    assert STAGE_TWO_CHECKPOINT in _checkpoints(tmp_path)
    cfg = dataclasses.replace(cfg, steps=4)
    with pytest.raises(
        TrainingDiverged, match=r"^training diverged at step \d+: the (loss is nan|model's .* not finite)$"
    ):
        train_dynamic(
            scene.model(), scene.views, _poisoned(scene.meshes), scene.cond, contact, cfg, checkpoint_dir=tmp_path
        )
    assert _checkpoints(tmp_path) == []


def test_the_advice_names_the_recipe_and_the_config_keys_of_its_rates() -> None:
    rates = learning_rates("stage.dynamic", DynamicTrainConfig(steps=1, lr_mlp=0.5), exclude=("lr_decay",))
    assert "stage.dynamic.lr_mlp" in rates and "stage.dynamic.lr_decay" not in rates
    with pytest.raises(TrainingDiverged) as caught, advising("stage two", rates):
        raise TrainingDiverged(7, "the loss is nan")
    message = str(caught.value)
    assert message.startswith("training diverged at step 7: the loss is nan; stage two ")
    assert "lower its learning rates (tenfold, say): stage.dynamic.lr_mlp=0.5, " in message
    assert "checkpoints were deleted" in message and caught.value.step == 7


SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "stage.capture.num_cameras=3",
    "fit.source=ground_truth",
    "run.progress=false",
    "stage.capture.cross_reenactment=false",
    "quality.warmup_steps=60",
    "stage.warmup.checkpoint_every=5",
]


def test_the_warmup_stage_says_which_keys_to_lower_and_leaves_no_checkpoint(tmp_path: Path) -> None:
    """The stage's one line: the stage, the step, ``stage.warmup.lr_*`` with their values, the stage's output folder;
    not the temporary folder its writer would have named; no checkpoint in ``.scratch`` to resume."""
    absurd = ["stage.warmup.lr_position_init=1e6", "stage.warmup.lr_scale=1e6"]
    with pytest.raises(StageFailed) as caught:
        run_app(compose_cfg([f"paths.outputs={tmp_path}", *SMALL, *absurd, "run.until=warmup"]))
    message = str(caught.value)
    subject = tmp_path / "synth_a"
    assert message.startswith("stage 'warmup' failed: TrainingDiverged: training diverged at step "), message
    assert "stage.warmup.lr_position_init=1e+06, " in message and "stage.warmup.lr_scale=1e+06, " in message
    assert message.endswith(f"nothing was written to {subject / 'methods' / 'interactavatar' / 'warmup'}"), message
    assert ".tmp" not in message
    scratch = subject / ".scratch"
    assert not scratch.exists() or not [p for p in scratch.rglob("*") if p.is_file()], list(scratch.rglob("*"))
    assert not (subject / "methods" / "interactavatar" / "warmup").exists()
