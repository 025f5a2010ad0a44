"""Degenerate and extreme inputs: outputs and gradients stay finite, culled Gaussians contribute nothing.

Every case renders a few ordinary Gaussians plus the extreme ones, in float32 (the training
dtype), through ``render_gaussians`` (torch backend), and backpropagates a loss on all outputs.
"""

from __future__ import annotations

import pytest
import torch
from gs_scenes import Scene, random_scene, single_gaussian

from avatar.render.gaussians import RenderOutput, render_gaussians

F32 = torch.float32


def _render(scene: Scene) -> RenderOutput:
    return render_gaussians(*scene.params(), *scene.camera(), backend="torch")


def _render_and_backward(scene: Scene) -> tuple[RenderOutput, list[torch.Tensor]]:
    """Render, backpropagate rgb + alpha + depth, and assert that everything is finite."""
    scene.requires_grad_()
    out = _render(scene)
    for name in ("rgb", "alpha", "depth"):
        assert torch.isfinite(getattr(out, name)).all(), name
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    grads = [p.grad for p in scene.params()]
    for name, g in zip(("means", "quats", "scales", "opacities", "colors"), grads):
        assert g is not None and torch.isfinite(g).all(), f"d/d{name}"
    assert torch.isfinite(out.grad2d()).all()
    return out, grads


def _with_extra(means: list[list[float]], *, scales: float | list[list[float]] = 0.05,
                quats: list[list[float]] | None = None, opacities: float = 0.9) -> Scene:
    """Five ordinary float32 Gaussians followed by extra ones at ``means``."""
    base = random_scene(5, seed=11, dtype=F32)
    n = len(means)
    extra = Scene(means=torch.tensor(means, dtype=F32),
                  quats=torch.tensor(quats if quats is not None else [[1.0, 0, 0, 0]] * n, dtype=F32),
                  scales=torch.tensor(scales, dtype=F32) if isinstance(scales, list) else torch.full((n, 3), scales),
                  opacities=torch.full((n,), opacities), colors=torch.linspace(0.1, 0.9, 3 * n).view(n, 3),
                  K=base.K, world_to_cam=base.world_to_cam, width=base.width, height=base.height,
                  background=base.background)
    return base.cat(extra)


def _camera_point(scene: Scene, p_cam: list[float]) -> list[float]:
    """World coordinates of a camera-space point of ``scene``'s camera."""
    view = scene.world_to_cam.double()
    world = torch.linalg.solve(view[:3, :3], torch.tensor(p_cam, dtype=torch.float64) - view[:3, 3])
    return world.tolist()


def _assert_same_image_as_base(out: RenderOutput, base_out: RenderOutput) -> None:
    for name in ("rgb", "alpha", "depth"):
        assert torch.allclose(getattr(out, name), getattr(base_out, name), atol=1e-6), name


@pytest.mark.parametrize("z", [-1.0, 0.0, 0.005, 0.01, 0.0100001, 1e-30, -1e-30])
def test_depth_at_behind_or_on_the_near_plane(z: float) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scene = _with_extra([_camera_point(base, [0.1, 0.05, z]), _camera_point(base, [0.0, 0.0, z])])
    out, _ = _render_and_backward(scene)
    if z < 0.01:  # culled by the near plane: contributes nothing
        assert (out.radii[5:] == 0).all()
        _assert_same_image_as_base(out, _render(base))


def test_behind_the_camera_contributes_nothing_and_gets_no_gradient() -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scene = _with_extra([_camera_point(base, [0.0, 0.0, -2.0])], scales=5.0)
    out, grads = _render_and_backward(scene)
    assert out.radii[5] == 0
    _assert_same_image_as_base(out, _render(base))
    assert all((g[5] == 0).all() for g in grads)
    assert out.grad2d_norm()[5] == 0


def test_gaussian_at_the_camera_centre() -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.0, 0.0, 0.0])]))
    assert out.radii[5] == 0


def test_zero_opacity_contributes_nothing() -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.0, 0.0, 2.0])], opacities=0.0))
    assert out.radii[5] == 0
    _assert_same_image_as_base(out, _render(base))


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-3, 10.0, 1e4, 1e10, 1e30])
def test_zero_tiny_and_huge_scales(scale: float) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.05, -0.05, 2.5])], scales=scale))
    assert out.radii[5] > 0


def test_degenerate_scales_per_axis() -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scales = [[0.0, 0.0, 0.1], [0.1, 0.0, 0.0], [1e6, 0.0, 1e-9]]
    _render_and_backward(_with_extra([_camera_point(base, [0.1 * i, 0.0, 2.0]) for i in range(3)], scales=scales))


def test_unnormalised_and_zero_quaternions() -> None:
    base = random_scene(5, seed=11, dtype=F32)
    means = [_camera_point(base, [0.1 * i - 0.2, 0.0, 2.0]) for i in range(4)]
    anisotropic = [[0.2, 0.02, 0.05]] * 4
    q = [0.3, -0.5, 0.7, 0.1]
    out, _ = _render_and_backward(_with_extra(means, scales=anisotropic,
                                              quats=[q, [100 * v for v in q], [0.0] * 4, [1e-30, 0.0, 0.0, 0.0]]))
    unit = _with_extra(means, scales=anisotropic, quats=[q, q, [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    assert torch.allclose(out.rgb, _render(unit).rgb, atol=1e-5)  # only the direction matters


def test_whole_image_gaussian_has_alpha_close_to_its_opacity() -> None:
    scene = single_gaussian(pixel=(11.5, 9.5), depth=2.0, sigma_px=2000.0, opacity=0.6, dtype=F32)
    out, _ = _render_and_backward(scene)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.6), atol=1e-4)
    expected_rgb = 0.6 * scene.colors[0] + 0.4 * scene.background
    assert torch.allclose(out.rgb, expected_rgb.expand_as(out.rgb), atol=1e-4)


def test_empty_scene_returns_the_background() -> None:
    scene = random_scene(0, seed=0, dtype=F32)
    out, _ = _render_and_backward(scene)
    assert out.rgb.shape == (scene.height, scene.width, 3)
    assert torch.equal(out.rgb, scene.background.expand_as(out.rgb))
    assert (out.alpha == 0).all() and (out.depth == 0).all()


def test_no_visible_gaussian_returns_the_background() -> None:
    scene = random_scene(4, seed=0, dtype=F32)
    scene.means = scene.means + torch.tensor([0.0, 0.0, -10.0]) @ scene.world_to_cam[:3, :3]  # all behind
    out, grads = _render_and_backward(scene)
    assert (out.radii == 0).all()
    assert torch.equal(out.rgb, scene.background.expand_as(out.rgb))
    assert all((g == 0).all() for g in grads)


def test_empty_tiles_around_a_small_gaussian() -> None:
    scene = single_gaussian(pixel=(2.0, 3.0), depth=2.0, sigma_px=0.8, opacity=0.9, width=40, height=36, dtype=F32)
    out, _ = _render_and_backward(scene)
    assert out.alpha[3, 2] > 0.5
    far_away = out.alpha[:, 20:]
    assert (far_away == 0).all()
    assert torch.equal(out.rgb[:, 20:], scene.background.expand(36, 20, 3))
