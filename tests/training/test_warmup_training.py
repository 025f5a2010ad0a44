"""The static warm-up loop: it learns, and a killed run resumes to exactly the uninterrupted result."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence
from avatar.representations.bound import warmup
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.training.validation import ValidationConfig, Validator


def _scene() -> tuple[ViewSet, MeshSequence]:
    """A red square (two triangles) 1 m in front of two 24 px cameras, over 2 frames."""
    verts = torch.tensor([[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.2, 0.2, 0.0], [-0.2, 0.2, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    size = 24
    K = torch.tensor([[40.0, 0, size / 2 - 0.5], [0, 40.0, size / 2 - 0.5], [0, 0, 1]])
    w2c = torch.eye(4).repeat(2, 1, 1)
    w2c[:, 2, 3] = 1.0
    w2c[1, 0, 3] = 0.05
    images = torch.zeros(2, 2, size, size, 3, dtype=torch.uint8)
    images[..., 0] = 60
    images[:, :, 4:20, 4:20] = torch.tensor([220, 40, 40], dtype=torch.uint8)
    labels = torch.zeros(2, 2, size, size, dtype=torch.uint8)
    labels[:, :, 4:20, 4:20] = 1
    views = ViewSet(images, labels, K.repeat(2, 1, 1), w2c, ["a", "b"], torch.tensor([60 / 255, 0.0, 0.0]))
    meshes = MeshSequence(verts.repeat(2, 1, 1), faces, torch.zeros(2, dtype=torch.long), ("face",))
    return views, meshes


def _model(meshes: MeshSequence) -> BoundGaussians:
    return BoundGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 8, init_opacity=0.3)


CFG = WarmupTrainConfig(
    steps=30,
    densify_from=0.2,
    densify_until=0.8,
    densify_interval=0.2,
    opacity_reset_interval=1.0,
    log_every=5,
    checkpoint_every=10,
    backend="torch",
)


def test_warmup_reduces_the_loss():
    views, meshes = _scene()
    log = train_warmup(_model(meshes), views, meshes, dataclasses.replace(CFG, steps=100, lr_color=0.02))
    assert log[-1].loss < 0.5 * log[0].loss, [r.loss for r in log]
    assert all(math.isfinite(r.loss) for r in log)


def test_killed_run_resumes_from_checkpoint_to_the_same_result(tmp_path, monkeypatch):
    views, meshes = _scene()
    reference = _model(meshes)
    ref_log = train_warmup(reference, views, meshes, CFG)

    _run_killed_at(17, tmp_path, monkeypatch)  # after the checkpoint of step 10
    assert (tmp_path / warmup.CHECKPOINT).is_file()

    resumed = _model(meshes)
    validator = Validator(ValidationConfig(), views)
    log = train_warmup(resumed, views, meshes, CFG, checkpoint_dir=tmp_path, validator=validator)
    assert validator.metrics()["resumed_from_step"] == 10  # the manifest says the run was resumed, and where
    assert [r.step for r in log] == [r.step for r in ref_log]
    assert resumed.num_gaussians == reference.num_gaussians
    for name, value in reference.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=1e-5, atol=1e-6)


def _run_killed_at(call: int, tmp_path, monkeypatch) -> None:
    """Run the warm-up into ``tmp_path`` and kill it at render call ``call`` (checkpoints every 10 steps)."""
    views, meshes = _scene()
    real_render = warmup.render_frame
    calls = {"n": 0}

    def dying_render(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == call:
            raise KeyboardInterrupt("killed")
        return real_render(*args, **kwargs)

    monkeypatch.setattr(warmup, "render_frame", dying_render)
    with pytest.raises(KeyboardInterrupt):
        train_warmup(_model(meshes), views, meshes, CFG, checkpoint_dir=tmp_path)
    monkeypatch.setattr(warmup, "render_frame", real_render)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "bit_flip"])
def test_a_corrupt_checkpoint_is_named_discarded_and_the_run_resumes_from_the_previous_one(
    tmp_path, monkeypatch, caplog, damage
):
    """Issue 9, case 5: verified on load; the newest is corrupt, so the run resumes from the one before it."""
    views, meshes = _scene()
    reference = _model(meshes)
    train_warmup(reference, views, meshes, CFG)
    _run_killed_at(27, tmp_path, monkeypatch)  # checkpoints of steps 10 (.prev) and 20
    newest = tmp_path / warmup.CHECKPOINT
    blob = bytearray(newest.read_bytes())
    if damage == "garbage":
        blob = bytearray(b"not a checkpoint at all")
    elif damage == "truncated":
        blob = blob[: len(blob) // 2]
    else:
        blob[len(blob) // 2] ^= 0x01
    newest.write_bytes(bytes(blob))

    resumed = _model(meshes)
    with caplog.at_level("WARNING"):
        log = train_warmup(resumed, views, meshes, CFG, checkpoint_dir=tmp_path)
    assert f"{newest}: checkpoint discarded" in caplog.text and "trying the previous one" in caplog.text
    assert log[-1].step == CFG.steps
    for name, value in reference.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=1e-5, atol=1e-6)


def test_with_every_checkpoint_corrupt_the_run_starts_over_instead_of_failing(tmp_path, monkeypatch, caplog):
    views, meshes = _scene()
    reference = _model(meshes)
    train_warmup(reference, views, meshes, CFG)
    _run_killed_at(27, tmp_path, monkeypatch)
    for path in (tmp_path / warmup.CHECKPOINT, tmp_path / f"{warmup.CHECKPOINT}.prev"):
        path.write_bytes(b"\0" * 100)
    fresh = _model(meshes)
    with caplog.at_level("WARNING"):
        train_warmup(fresh, views, meshes, CFG, checkpoint_dir=tmp_path)
    assert "starting over" in caplog.text
    for name, value in reference.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[name], value, rtol=1e-5, atol=1e-6)
