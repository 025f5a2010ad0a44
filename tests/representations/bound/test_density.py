"""Density control keeps every Gaussian bound, never empties a triangle, and keeps Adam in step."""

from __future__ import annotations

import math

import torch

from avatar.representations.bound.density import DensityConfig, DensityController, reset_opacity
from avatar.representations.bound.gaussians import BoundGaussians

CFG = DensityConfig(densify_from=1, densify_until=100, densify_interval=1, opacity_reset_interval=1000)


def _model(per_triangle: int = 2) -> tuple[BoundGaussians, torch.Tensor, torch.Tensor]:
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2], [2, 0, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [1, 4, 3]])
    model = BoundGaussians.on_triangles(verts, faces, torch.tensor([0, 0, 1]), per_triangle)
    return model, verts, faces


def _adam(model: BoundGaussians) -> torch.optim.Adam:
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    loss = sum(p.square().sum() for p in model.parameters())
    loss.backward()
    opt.step()
    return opt


def _check_optimizer_consistent(model: BoundGaussians, opt: torch.optim.Adam) -> None:
    params = list(model.parameters())
    assert {id(p) for p in opt.param_groups[0]["params"]} == {id(p) for p in params}
    for p in params:
        state = opt.state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape
    # And it can take another step.
    opt.zero_grad()
    sum(p.square().sum() for p in model.parameters()).backward()
    opt.step()


def test_initialisation_places_gaussians_on_their_triangles():
    model, verts, faces = _model(per_triangle=5)
    assert model.num_gaussians == 15
    assert torch.equal(model.binding, torch.arange(3).repeat_interleave(5))
    means, scales, _ = model.world(verts, faces)
    # Every mean lies in the plane of its triangle and inside it (barycentric coordinates >= 0).
    tri = verts[faces][model.binding]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert torch.allclose(((means - tri[:, 0]) * n).sum(-1), torch.zeros(15), atol=1e-6)
    centroid = tri.mean(1)
    assert torch.allclose(means[::5], centroid[::5], atol=1e-6)
    assert (scales > 0).all()


def test_clone_keeps_binding_and_moments():
    model, verts, faces = _model()
    opt = _adam(model)
    ctrl = DensityController(CFG, model.num_gaussians)
    grads = torch.zeros(6)
    grads[[1, 4]] = 1.0  # two hot Gaussians
    ctrl.accumulate(grads, torch.ones(6, dtype=torch.bool), image_size=64)
    _, scales, _ = model.world(verts, faces)
    out = ctrl.step(1, model, opt, scales, extent=1e3)  # huge extent: everything counts as small -> clone
    assert out["cloned"] == 2 and out["split"] == 0
    assert model.num_gaussians == 8
    assert torch.equal(model.binding[-2:], torch.tensor([0, 2]))
    assert torch.equal(model.local_means[-2:], model.local_means[[1, 4]])
    _check_optimizer_consistent(model, opt)


def test_split_replaces_parent_with_two_smaller_children_on_the_same_triangle():
    model, verts, faces = _model()
    opt = _adam(model)
    ctrl = DensityController(CFG, model.num_gaussians)
    grads = torch.zeros(6)
    grads[3] = 1.0
    ctrl.accumulate(grads, torch.ones(6, dtype=torch.bool), image_size=64)
    parent_scale = model.log_scales[3].detach().clone()
    _, scales, _ = model.world(verts, faces)
    out = ctrl.step(1, model, opt, scales, extent=1e-6)  # tiny extent: everything is big -> split
    assert out["split"] == 1 and model.num_gaussians == 7
    assert torch.equal(model.binding[-2:], torch.tensor([1, 1]))
    assert torch.allclose(model.log_scales[-2:], (parent_scale - math.log(1.6)).expand(2, 3))
    _check_optimizer_consistent(model, opt)


def test_prune_never_leaves_a_triangle_empty():
    model, _, _ = _model(per_triangle=3)
    opt = _adam(model)
    with torch.no_grad():
        model.opacity_logits[:] = -20.0  # everything transparent
        model.opacity_logits[4] = -15.0  # the most opaque of triangle 1
        model.local_means[7] = float("nan")  # a broken Gaussian on triangle 2
    ctrl = DensityController(CFG, model.num_gaussians)
    ctrl.step(1, model, opt, torch.ones(9, 3), extent=1.0)
    assert sorted(model.binding.tolist()) == [0, 1, 2]
    assert 1 in model.binding.tolist() and model.opacity_logits[model.binding == 1].item() == -15.0
    assert all(torch.isfinite(p).all() for p in model.parameters())
    _check_optimizer_consistent(model, opt)


def test_prune_removes_transparent_and_nan_gaussians_when_others_remain():
    model, _, _ = _model(per_triangle=3)
    opt = _adam(model)
    with torch.no_grad():
        model.opacity_logits[[0, 3]] = -20.0
        model.quats[6] = float("nan")
    ctrl = DensityController(CFG, model.num_gaussians)
    out = ctrl.step(1, model, opt, torch.ones(9, 3), extent=1.0)
    assert out["pruned"] == 3 and model.num_gaussians == 6
    assert sorted(model.binding.tolist()) == [0, 0, 1, 1, 2, 2]


def test_opacity_reset_caps_and_zeroes_moments():
    model, _, _ = _model()
    opt = _adam(model)
    with torch.no_grad():
        model.opacity_logits[:] = 3.0
        model.opacity_logits[0] = -10.0
    reset_opacity(model, opt, 0.01)
    assert torch.all(model.opacities() <= 0.01 + 1e-6)
    assert model.opacity_logits[0].item() == -10.0
    assert torch.count_nonzero(opt.state[model.opacity_logits]["exp_avg"]) == 0
    _check_optimizer_consistent(model, opt)


def test_schedule_window_and_cap():
    cfg = DensityConfig(
        densify_from=10, densify_until=20, densify_interval=5, opacity_reset_interval=15, max_gaussians=7
    )
    model, verts, faces = _model()
    opt = _adam(model)
    ctrl = DensityController(cfg, model.num_gaussians)
    assert ctrl.step(5, model, opt, torch.ones(6, 3), 1.0)["cloned"] == 0  # before the window
    ctrl.accumulate(torch.ones(6), torch.ones(6, dtype=torch.bool), 64)
    out = ctrl.step(10, model, opt, torch.zeros(6, 3), 1.0)
    assert out["cloned"] == 1 and model.num_gaussians == 7  # capped at max_gaussians
    assert ctrl.step(15, model, opt, torch.zeros(7, 3), 1.0)["reset"] == 7
    assert ctrl.step(25, model, opt, torch.zeros(7, 3), 1.0) == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
