"""Density control of embedded Gaussians: clone, split (children walk), prune, opacity reset."""

from __future__ import annotations

import math

import torch

from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded.density import EmbeddedDensityConfig, EmbeddedDensityController
from avatar.representations.embedded.embedding import PARAM_NAMES
from avatar.representations.embedded.training import SplattingConfig, splatting_param_groups
from tests.representations.embedded.meshes import hand_and_head

EXTENT = 1.0


def _setup(seed: int = 0) -> tuple[EmbeddedGaussians, torch.optim.Adam, torch.Tensor]:
    verts, faces, face_part = hand_and_head(torch.float32)
    model = EmbeddedGaussians.on_triangles(verts, faces, face_part, 1, init_opacity=0.3, seed=seed)
    optimizer = torch.optim.Adam(splatting_param_groups(model, SplattingConfig(steps=10)), lr=0.0, eps=1e-15)
    means, scales, quats = model.world(verts * 1.05, faces)
    (means.sum() + scales.sum() + quats.sum() + model.opacities().sum() + model.colors().sum()).backward()
    optimizer.step()  # every parameter now has Adam moments
    optimizer.zero_grad(set_to_none=True)
    return model, optimizer, face_part


def _controller(n: int, **overrides) -> EmbeddedDensityController:
    cfg = EmbeddedDensityConfig(
        densify_from=1, densify_until=10, densify_interval=1, opacity_reset_interval=100, **overrides
    )
    return EmbeddedDensityController(cfg, n, seed=3)


def _assert_valid(model: EmbeddedGaussians, optimizer: torch.optim.Adam, face_part: torch.Tensor) -> None:
    n = model.num_gaussians
    assert bool(((model.triangle >= 0) & (model.triangle < model.mesh.faces.shape[0])).all())
    uv = model.barycentric.detach()
    assert bool((uv >= -1e-6).all()) and bool((uv.sum(-1) <= 1 + 1e-6).all())
    assert torch.equal(face_part[model.triangle], model.part)
    groups = {g["name"]: g["params"][0] for g in optimizer.param_groups}
    for name in PARAM_NAMES:
        param = getattr(model, name)
        assert groups[name] is param and param.shape[0] == n, name
        for key in ("exp_avg", "exp_avg_sq"):
            assert optimizer.state[param][key].shape == param.shape, (name, key)


def test_clone_split_and_prune_keep_every_gaussian_on_a_valid_triangle():
    model, optimizer, face_part = _setup()
    n = model.num_gaussians
    gen = torch.Generator().manual_seed(1)
    role = torch.randint(5, (n,), generator=gen)  # 0 clone, 1 split, 2 prune, 3-4 untouched
    with torch.no_grad():
        model.log_scales[role == 0] = math.log(0.002)  # below percent_dense * extent = 0.01
        model.log_scales[role == 1] = math.log(0.05)  # above it
        model.opacity_logits[role == 2] = -8.0  # opacity < 0.005
    density = _controller(n)
    hot = torch.where(role <= 1, 1.0, 0.0)  # px gradient: NDC 1.0 * 32 / 2 >> 2e-4
    density.accumulate(1, hot, torch.full((n,), 3, dtype=torch.int32), image_size=32)
    canonical_before = model.world(model.mesh.vertices, model.mesh.faces)[0].detach()
    split_parents = torch.nonzero(role == 1).flatten()
    done = density.step(1, model, optimizer, EXTENT)
    cloned, split, pruned = int((role == 0).sum()), int((role == 1).sum()), int((role == 2).sum())
    assert (done["cloned"], done["split"], done["pruned"]) == (cloned, split, pruned)
    assert model.num_gaussians == n + cloned + split - pruned
    assert done["walked"] > 0  # some children left the parent's triangle and walked
    _assert_valid(model, optimizer, face_part)
    # survivors (the originals of clones too) first, in their order, then clones, then two children per
    # split parent
    survivors = torch.nonzero((role != 1) & (role != 2)).flatten()
    clones = torch.nonzero(role == 0).flatten()
    first_child = len(survivors) + len(clones)
    children = model.world(model.mesh.vertices, model.mesh.faces)[0].detach()[first_child:]
    assert children.shape[0] == 2 * split
    expected = torch.full((2 * split, 3), math.log(0.05 / 1.6))
    torch.testing.assert_close(model.log_scales.detach()[first_child:], expected)
    # children are drawn from the parent's Gaussian: within a few sigma (0.05) of it
    parent_means = canonical_before[split_parents.repeat(2)]
    assert float((children - parent_means).norm(dim=-1).max()) < 6 * 0.05
    for name in PARAM_NAMES:  # new rows start with zero moments, kept rows keep theirs
        state = optimizer.state[getattr(model, name)]
        assert float(state["exp_avg_sq"][len(survivors) :].abs().max()) == 0.0, name
        assert float(state["exp_avg_sq"][: len(survivors)].abs().max()) > 0.0, name
    assert density.grad_sum.shape == (model.num_gaussians,)


def test_opacity_reset_caps_opacities_and_zeroes_their_moments():
    model, optimizer, _ = _setup()
    cfg = EmbeddedDensityConfig(densify_from=100, densify_until=10, densify_interval=100, opacity_reset_interval=5)
    density = EmbeddedDensityController(cfg, model.num_gaussians)
    assert density.step(5, model, optimizer, EXTENT)["reset"] == model.num_gaussians
    assert float(model.opacities().detach().max()) <= 0.01 + 1e-6
    assert float(optimizer.state[model.opacity_logits]["exp_avg"].abs().max()) == 0.0


def test_densify_until_zero_disables_density_control():
    model, optimizer, _ = _setup()
    n = model.num_gaussians
    cfg = EmbeddedDensityConfig(densify_from=1, densify_until=0, densify_interval=1, opacity_reset_interval=1)
    density = EmbeddedDensityController(cfg, n)
    before = model.state_tensors()
    density.accumulate(1, torch.ones(n), torch.full((n,), 3, dtype=torch.int32), image_size=32)
    assert density.step(1, model, optimizer, EXTENT) == {"cloned": 0, "split": 0, "pruned": 0, "walked": 0, "reset": 0}
    for name, value in before.items():
        assert torch.equal(model.state_tensors()[name], value)
    assert float(density.grad_sum.sum()) == 0.0


def test_pruning_never_empties_the_model():
    model, optimizer, face_part = _setup()
    with torch.no_grad():
        model.opacity_logits.fill_(-10.0)
        model.opacity_logits[7] = -9.0
    density = _controller(model.num_gaussians)
    density.step(1, model, optimizer, EXTENT)
    assert model.num_gaussians == 1
    _assert_valid(model, optimizer, face_part)
