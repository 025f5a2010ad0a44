"""The SplattingAvatar training loop: it learns, Gaussians walk, a killed run resumes bit for bit,
and a second call without density control continues the same model."""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
import torch

from avatar.geometry.views import ViewSet
from avatar.metrics import LPIPSWeightsNotFoundError
from avatar.metrics.lpips_weights import weight_file
from avatar.posing import MeshSequence
from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded import training as splatting
from avatar.representations.embedded.training import SplattingConfig, render_splatting, scale_penalty, train_splatting
from tests.representations.embedded.meshes import bumpy, grid

try:
    weight_file("alex")
    LPIPS_WEIGHT = 0.05  # the public recipe
except LPIPSWeightsNotFoundError:
    LPIPS_WEIGHT = 0.0

SIZE = 32


def _scene() -> tuple[ViewSet, MeshSequence]:
    """A 0.4 m square (a 4 x 4 vertex grid), flat then bent, 1 m in front of two 32 px cameras, whose
    images are renders of a striped ground-truth model."""
    verts, faces = grid(4, dtype=torch.float32)
    frames = torch.stack([verts, bumpy(verts.double()).float()])
    meshes = MeshSequence(frames, faces, torch.zeros(faces.shape[0], dtype=torch.long), ("face",))
    K = torch.tensor([[60.0, 0, SIZE / 2 - 0.5], [0, 60.0, SIZE / 2 - 0.5], [0, 0, 1]])
    w2c = torch.eye(4).repeat(2, 1, 1)
    w2c[:, 2, 3] = 1.0
    w2c[1, 0, 3] = 0.05
    background = torch.tensor([0.2, 0.2, 0.2])
    truth = EmbeddedGaussians.on_triangles(verts, faces, meshes.face_part, 12, init_opacity=0.9, seed=7)
    means, _, _ = truth.world(verts, faces)
    stripes = (torch.sin(means[:, 0].detach() * 40) > 0).float()
    truth.set_colors(torch.stack([0.9 * stripes + 0.05, 0.3 * torch.ones_like(stripes), 0.9 - 0.8 * stripes], -1))
    images = torch.zeros(2, 2, SIZE, SIZE, 3, dtype=torch.uint8)
    views = ViewSet(
        images, torch.zeros(2, 2, SIZE, SIZE, dtype=torch.uint8), K.repeat(2, 1, 1), w2c, ["a", "b"], background
    )
    with torch.no_grad():
        for f in range(2):
            for c in range(2):
                out, _ = render_splatting(truth, meshes, views, f, c, backend="torch")
                views.images[f, c] = (out.rgb.clamp(0, 1) * 255).round().to(torch.uint8)
                views.labels[f, c] = (out.alpha > 0.5).to(torch.uint8)
    return views, meshes


def _model(meshes: MeshSequence) -> EmbeddedGaussians:
    return EmbeddedGaussians.on_triangles(
        meshes.vertices[0], meshes.faces, meshes.face_part, 4, init_opacity=0.3, seed=0
    )


# Larger position learning rates than the recipe's so that Gaussians walk within 30 steps.
CFG = SplattingConfig(
    steps=30,
    lambda_lpips=LPIPS_WEIGHT,
    lr_position_init=0.02,
    lr_position_final=0.005,
    lr_color=0.03,
    densify_from=0.2,
    densify_until=0.8,
    densify_interval=0.2,
    opacity_reset_interval=1.0,
    walk_every=3,
    log_every=5,
    checkpoint_every=10,
    backend="torch",
)


@pytest.fixture(scope="module")
def scene() -> tuple[ViewSet, MeshSequence]:
    return _scene()


def test_training_lowers_the_loss_and_gaussians_walk(scene):
    views, meshes = scene
    model = _model(meshes)
    log = train_splatting(model, views, meshes, CFG)
    assert [r.step for r in log] == [5, 10, 15, 20, 25, 30]
    assert all(math.isfinite(r.loss) for r in log)
    assert log[-1].loss < 0.7 * log[0].loss, [r.loss for r in log]
    assert sum(r.walked for r in log) > 0
    uv = model.barycentric.detach()
    assert bool((uv >= -1e-6).all()) and bool((uv.sum(-1) <= 1 + 1e-6).all())
    if LPIPS_WEIGHT:
        assert log[0].lpips > 0


def test_killed_run_resumes_from_its_checkpoint_bit_for_bit(scene, tmp_path, monkeypatch):
    views, meshes = scene
    reference = _model(meshes)
    ref_log = train_splatting(reference, views, meshes, CFG)

    renders = itertools.count(1)
    original = splatting.render_splatting

    def killed_at_render_17(*args, **kwargs):  # after the checkpoint of step 10
        if next(renders) == 17:
            raise KeyboardInterrupt("killed")
        return original(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(splatting, "render_splatting", killed_at_render_17)
        with pytest.raises(KeyboardInterrupt):
            train_splatting(_model(meshes), views, meshes, CFG, checkpoint_dir=tmp_path)
    assert (tmp_path / splatting.CHECKPOINT).is_file()

    resumed = _model(meshes)
    log = train_splatting(resumed, views, meshes, CFG, checkpoint_dir=tmp_path)
    assert log == ref_log
    assert resumed.num_gaussians == reference.num_gaussians
    for name, value in reference.state_dict().items():
        assert torch.equal(resumed.state_dict()[name], value), name


def test_a_second_run_without_density_control_keeps_the_count_and_walks(scene):
    views, meshes = scene
    model = _model(meshes)
    train_splatting(model, views, meshes, dataclasses.replace(CFG, steps=10))
    count = model.num_gaussians
    stage_two = dataclasses.replace(
        CFG,
        steps=12,
        densify_until=0.0,
        seed=1,
        lr_position_init=0.05,
        lr_position_final=0.05,
        walk_every=1,
        log_every=4,
    )
    log = train_splatting(model, views, meshes, stage_two)
    assert [r.num_gaussians for r in log] == [count] * 3
    assert sum(r.walked for r in log) > 0


def test_scale_penalty_takes_only_needle_like_gaussians():
    scales = torch.tensor(
        [
            [0.02, 0.001, 0.001],  # needle: 0.02 > 0.008 and ratio 20 > 10
            [0.02, 0.01, 0.01],  # large but round
            [0.005, 0.0001, 0.0001],  # thin but small
            [0.04, 0.002, 0.003],
        ]
    )  # needle
    torch.testing.assert_close(scale_penalty(scales, 0.008, 10.0), torch.tensor(0.03))
    assert float(scale_penalty(scales[1:3], 0.008, 10.0)) == 0.0
