"""Degenerate and extreme inputs: outputs and gradients stay finite, culled Gaussians contribute nothing.

Every case renders a few ordinary Gaussians plus the extreme ones, in float32 (the training
dtype), through ``render_gaussians`` with each backend (``torch``; the compiled ``cpu`` when it is built;
``gsplat`` through its PyTorch reference on the CPU, ``gsplat_reference.py``, and through its CUDA kernels
where a GPU is present), the last ones giving the torch backend's images and gradients to 1e-5, and
backpropagates a loss on all outputs.

gsplat's documented differences (``backend_gsplat``), where a case meets them:

* depth ties: gsplat computes camera depth in float32 from the world means, the project in float64, so
  Gaussians at equal depth (``depth_ties``) can composite in another order: there only alpha (which does not
  depend on the order) and finiteness are compared;
* ill-conditioned 2D covariances: gsplat inverts them in float32, where ``[1e6, 0, 1e-9]`` loses everything
  to cancellation (the project's backends work in float64): finiteness only;
* radii: gsplat's scale cap (``MAX_STD_PX``) bounds a huge Gaussian's radius at a few million pixels, the
  project's at 2^30: equal below a million, both beyond it above.
"""

from __future__ import annotations

import pytest
import torch
from gs_scenes import Scene, random_scene, single_gaussian

from avatar.render.gaussians import RenderOutput, render_gaussians
from avatar.render.gaussians.extension import cpu_extension_available, unavailable_reason
from tests.float_agreement import assert_rounded_alike

F32 = torch.float32
NAMES = ("means", "quats", "scales", "opacities", "colors")
#: gradient tolerance relative to the largest entry where it is not 1e-5: gsplat's CUDA kernels (fast math,
#: atomics: 2.6e-5 to 6.7e-5 measured on an H200; where T crosses the 1e-4 stop, __expf can blend one Gaussian
#: more or less, about 1e-4 x alpha in its colour gradient)
GRAD_TOL = {"gsplat-cuda": 1e-4}


@pytest.fixture(params=["torch", "cpu", "gsplat-reference", pytest.param("gsplat-cuda", marks=pytest.mark.cuda)])
def backend(request: pytest.FixtureRequest) -> str:
    """The backend name to render with; ``gsplat-*`` render with ``gsplat`` on the kernels named."""
    if request.param == "cpu" and not cpu_extension_available():
        pytest.skip(f"compiled CPU rasterizer not built: {unavailable_reason()}")
    if request.param.startswith("gsplat-"):
        request.getfixturevalue(request.param.replace("-", "_"))
    return request.param


def _name(backend: str) -> str:
    """The ``render_gaussians`` backend of a fixture value (``gsplat-reference`` and ``gsplat-cuda``: gsplat)."""
    return backend.split("-")[0]


def _render(scene: Scene, backend: str = "torch") -> RenderOutput:
    return render_gaussians(*scene.params(), *scene.camera(), backend=_name(backend))


def _backward(scene: Scene, backend: str) -> tuple[RenderOutput, list[torch.Tensor]]:
    params = [p.detach().clone().requires_grad_(True) for p in scene.params()]
    out = render_gaussians(*params, *scene.camera(), backend=_name(backend))
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    return out, [p.grad for p in params]


def _render_and_backward(
    scene: Scene, backend: str, ill_conditioned: tuple[int, ...] = (), depth_ties: bool = False
) -> tuple[RenderOutput, list[torch.Tensor]]:
    """Render, backpropagate rgb + alpha + depth, and assert that everything is finite (and, for the
    compiled backend and gsplat, equal to the torch backend's to 1e-5).

    ``ill_conditioned``: Gaussians whose gradients are checked for finiteness only, not against the torch
    backend, because two correct evaluation orders of them disagree by more than 1e-5 (see the caller).
    ``depth_ties``: the scene has overlapping Gaussians at equal depth (see the module docstring for gsplat).
    """
    out, grads = _backward(scene, backend)
    for name in ("rgb", "alpha", "depth"):
        assert torch.isfinite(getattr(out, name)).all(), name
    for name, g in zip(NAMES, grads):
        assert g is not None and torch.isfinite(g).all(), f"d/d{name}"
    assert torch.isfinite(out.grad2d()).all()
    if _name(backend) == "gsplat" and ill_conditioned:
        return out, grads
    if _name(backend) == "gsplat" and depth_ties:
        ref = _render(scene, "torch")
        assert torch.allclose(out.alpha, ref.alpha, rtol=0, atol=1e-5)
        _assert_same_radii(out, ref, backend)
        return out, grads
    if backend != "torch":
        ref, ref_grads = _backward(scene, "torch")
        for name in ("rgb", "alpha", "depth"):
            assert torch.allclose(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-5), name
        _assert_same_radii(out, ref, backend)
        compared = [i for i in range(scene.means.shape[0]) if i not in ill_conditioned]
        for name, g, r in zip((*NAMES, "means2d"), [*grads, out.grad2d()], [*ref_grads, ref.grad2d()]):
            g, r = g[compared], r[compared]
            # 1e-5 of the largest entry; the 1e-6 floor covers inputs whose gradient is float32 rounding noise.
            tol = GRAD_TOL.get(backend, 1e-5) * r.abs().amax(dim=None) + 1e-6 if r.numel() else 0.0
            assert ((g - r).abs() <= tol).all(), f"d/d{name} differs from the torch backend"
    return out, grads


def _assert_same_radii(out: RenderOutput, ref: RenderOutput, backend: str) -> None:
    """The compiled backend's radii are the torch backend's (one pixel apart where a radius lands on an
    integer: two implementations, tests/float_agreement.py); gsplat's too, below the scale cap's radius."""
    if _name(backend) != "gsplat":
        assert_rounded_alike(out.radii, ref.radii, at_most=1, what="radii")
        return
    huge = ref.radii > 1_000_000
    assert_rounded_alike(out.radii[~huge], ref.radii[~huge], at_most=1, what="radii")
    assert (out.radii[huge] > 1_000_000).all()


def _with_extra(
    means: list[list[float]],
    *,
    scales: float | list[list[float]] = 0.05,
    quats: list[list[float]] | None = None,
    opacities: float = 0.9,
) -> Scene:
    """Five ordinary float32 Gaussians followed by extra ones at ``means``."""
    base = random_scene(5, seed=11, dtype=F32)
    n = len(means)
    extra = Scene(
        means=torch.tensor(means, dtype=F32),
        quats=torch.tensor(quats if quats is not None else [[1.0, 0, 0, 0]] * n, dtype=F32),
        scales=torch.tensor(scales, dtype=F32) if isinstance(scales, list) else torch.full((n, 3), scales),
        opacities=torch.full((n,), opacities),
        colors=torch.linspace(0.1, 0.9, 3 * n).view(n, 3),
        K=base.K,
        world_to_cam=base.world_to_cam,
        width=base.width,
        height=base.height,
        background=base.background,
    )
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
def test_depth_at_behind_or_on_the_near_plane(z: float, backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scene = _with_extra([_camera_point(base, [0.1, 0.05, z]), _camera_point(base, [0.0, 0.0, z])])
    out, _ = _render_and_backward(scene, backend, depth_ties=True)
    if z < 0.01:  # culled by the near plane: contributes nothing
        assert (out.radii[5:] == 0).all()
        _assert_same_image_as_base(out, _render(base, backend))


def test_behind_the_camera_contributes_nothing_and_gets_no_gradient(backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scene = _with_extra([_camera_point(base, [0.0, 0.0, -2.0])], scales=5.0)
    out, grads = _render_and_backward(scene, backend)
    assert out.radii[5] == 0
    _assert_same_image_as_base(out, _render(base, backend))
    assert all((g[5] == 0).all() for g in grads)
    assert out.grad2d_norm()[5] == 0


def test_gaussian_at_the_camera_centre(backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.0, 0.0, 0.0])]), backend)
    assert out.radii[5] == 0


def test_zero_opacity_contributes_nothing(backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.0, 0.0, 2.0])], opacities=0.0), backend)
    assert out.radii[5] == 0
    _assert_same_image_as_base(out, _render(base, backend))


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-3, 10.0, 1e4, 1e10, 1e30])
def test_zero_tiny_and_huge_scales(scale: float, backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    out, _ = _render_and_backward(_with_extra([_camera_point(base, [0.05, -0.05, 2.5])], scales=scale), backend)
    assert out.radii[5] > 0


def test_degenerate_scales_per_axis(backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    scales = [[0.0, 0.0, 0.1], [0.1, 0.0, 0.0], [1e6, 0.0, 1e-9]]
    means = [_camera_point(base, [0.1 * i, 0.0, 2.0]) for i in range(3)]
    # The last one (scale 1e6 beside 0 and 1e-9) has a 2D covariance of ~1e14 whose inverse is formed by
    # cancellation: its mean and quaternion gradients differ between the two backends by 7e-5 (means) and
    # 2e-2 (quats) of their size even in float64, and their float32 values are off the float64 ones by 1.5-2.4.
    # Its image and the other Gaussians' gradients are still compared; its own only need to be finite.
    _render_and_backward(
        _with_extra(means, scales=scales), backend, ill_conditioned=(base.means.shape[0] + 2,), depth_ties=True
    )


def test_unnormalised_and_zero_quaternions(backend: str) -> None:
    base = random_scene(5, seed=11, dtype=F32)
    means = [_camera_point(base, [0.1 * i - 0.2, 0.0, 2.0]) for i in range(4)]
    anisotropic = [[0.2, 0.02, 0.05]] * 4
    q = [0.3, -0.5, 0.7, 0.1]
    out, _ = _render_and_backward(
        _with_extra(means, scales=anisotropic, quats=[q, [100 * v for v in q], [0.0] * 4, [1e-30, 0.0, 0.0, 0.0]]),
        backend,
        depth_ties=True,
    )
    unit = _with_extra(means, scales=anisotropic, quats=[q, q, [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    assert torch.allclose(out.rgb, _render(unit, backend).rgb, atol=1e-5)  # only the direction matters


def test_whole_image_gaussian_has_alpha_close_to_its_opacity(backend: str) -> None:
    scene = single_gaussian(pixel=(11.5, 9.5), depth=2.0, sigma_px=2000.0, opacity=0.6, dtype=F32)
    out, _ = _render_and_backward(scene, backend)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.6), atol=1e-4)
    expected_rgb = 0.6 * scene.colors[0] + 0.4 * scene.background
    assert torch.allclose(out.rgb, expected_rgb.expand_as(out.rgb), atol=1e-4)


def test_empty_scene_returns_the_background(backend: str) -> None:
    scene = random_scene(0, seed=0, dtype=F32)
    out, _ = _render_and_backward(scene, backend)
    assert out.rgb.shape == (scene.height, scene.width, 3)
    assert torch.equal(out.rgb, scene.background.expand_as(out.rgb))
    assert (out.alpha == 0).all() and (out.depth == 0).all()


def test_no_visible_gaussian_returns_the_background(backend: str) -> None:
    scene = random_scene(4, seed=0, dtype=F32)
    scene.means = scene.means + torch.tensor([0.0, 0.0, -10.0]) @ scene.world_to_cam[:3, :3]  # all behind
    out, grads = _render_and_backward(scene, backend)
    assert (out.radii == 0).all()
    assert torch.equal(out.rgb, scene.background.expand_as(out.rgb))
    assert all((g == 0).all() for g in grads)


def test_empty_tiles_around_a_small_gaussian(backend: str) -> None:
    scene = single_gaussian(pixel=(2.0, 3.0), depth=2.0, sigma_px=0.8, opacity=0.9, width=40, height=36, dtype=F32)
    out, _ = _render_and_backward(scene, backend)
    assert out.alpha[3, 2] > 0.5
    far_away = out.alpha[:, 20:]
    assert (far_away == 0).all()
    assert torch.equal(out.rgb[:, 20:], scene.background.expand(36, 20, 3))


def test_ten_thousand_gaussians_at_one_point(backend: str) -> None:
    """10k identical Gaussians on one pixel: one tile list of 10k equal depths (ties keep the index
    order), the pixel stops after a few of them, and the gradient still reaches every input."""
    base = random_scene(5, seed=11, dtype=F32)
    n = 10_000
    scene = _with_extra([_camera_point(base, [0.02, 0.01, 2.0])] * n, scales=0.02, opacities=0.5)
    out, grads = _render_and_backward(scene, backend)
    assert (out.radii[5:] > 0).all()
    assert out.alpha.max() > 0.99
    assert (grads[4][5:].abs().sum(-1) > 0).sum() < n  # only the front of the stack is blended
