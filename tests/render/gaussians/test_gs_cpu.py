"""The compiled CPU backend against the brute-force renderer and the torch backend.

Tolerances as the torch backend's: float64 images to 1e-10 absolute and gradients to 1e-10
relative to the largest reference entry of each input (observed: ~1e-15); float32 to 1e-5
(observed: ~1e-7 on images, ~1e-6 on gradients); means2d to 4 ULPs, and radii to one pixel in 1 % of
the Gaussians (tests/float_agreement.py: the two round differently on some CPUs). Thread count and
tile size never change the image bit for bit (every pixel composites the same list in the same order); the thread count
does not change the gradients either (per-pair gradients are summed in a fixed order).
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import gs_bruteforce as brute
import pytest
import torch
from gs_scenes import Scene, random_scene, single_gaussian

from avatar.render.gaussians import extension, render_gaussians
from avatar.render.gaussians.backend_cpu import render_cpu, work_counts
from avatar.render.gaussians.backend_torch import render_torch
from avatar.render.gaussians.render import resolve_backend
from tests.float_agreement import assert_rounded_alike, assert_within_ulps

pytestmark = pytest.mark.skipif(
    not extension.cpu_extension_available(),
    reason=f"compiled CPU rasterizer not built: {extension.unavailable_reason()}",
)

OUTPUTS = ("rgb", "alpha", "depth")
NAMES = ("means", "quats", "scales", "opacities", "colors", "background")
TOL = {torch.float64: 1e-10, torch.float32: 1e-5}


def _weights(scene: Scene, seed: int = 7) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = {
        "rgb": (scene.height, scene.width, 3),
        "alpha": (scene.height, scene.width),
        "depth": (scene.height, scene.width),
    }
    return {k: torch.rand(shape, generator=g, dtype=torch.float64).to(scene.means.dtype) for k, shape in shapes.items()}


def _inputs(scene: Scene) -> list[torch.Tensor]:
    """The differentiable inputs: the five Gaussian parameters and the background."""
    return [*scene.params(), scene.background]


def _images_and_grads(
    render: Callable[..., Any], scene: Scene, **kwargs: Any
) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    """Images (detached) and gradients of a weighted sum of them w.r.t. every input and means2d."""
    inputs = [t.detach().clone().requires_grad_(True) for t in _inputs(scene)]
    out = render(*inputs[:5], scene.K, scene.world_to_cam, scene.width, scene.height, inputs[5], **kwargs)
    images = {"rgb": out.rgb, "alpha": out.alpha, "depth": out.depth}
    weights = _weights(scene)
    grads = torch.autograd.grad(sum((images[k] * weights[k]).sum() for k in OUTPUTS), [*inputs, out.means2d])
    return {k: v.detach() for k, v in images.items()}, list(grads)


def _assert_close(got: tuple, ref: tuple, tol: float) -> None:
    images, grads = got
    ref_images, ref_grads = ref
    for k in OUTPUTS:
        err = (images[k].double() - ref_images[k].double()).abs().max().item()
        assert err <= tol, f"{k}: max abs error {err:.3e}"
    for name, g, r in zip((*NAMES, "means2d"), grads, ref_grads):
        assert torch.isfinite(g).all(), name
        err = ((g.double() - r.double()).abs().max() / r.double().abs().max().clamp_min(1e-30)).item()
        assert err <= tol, f"d/d{name}: relative error {err:.3e}"


def _bruteforce(scene: Scene) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    return _images_and_grads(lambda *args: SimpleNamespace(**brute.render(*args)), scene)


@pytest.mark.parametrize("tile_size", [8, 16])
@pytest.mark.parametrize("seed,n", [(0, 10), (1, 20), (2, 30)])
def test_float64_matches_bruteforce(seed: int, n: int, tile_size: int) -> None:
    scene = random_scene(n, seed)
    _assert_close(_images_and_grads(render_cpu, scene, tile_size=tile_size), _bruteforce(scene), 1e-10)


def test_early_stop_matches_bruteforce() -> None:
    """A deep stack of large, fairly opaque Gaussians: most pixels stop before the end of the list."""
    scene = random_scene(40, seed=3, scale=1.0)
    scene.opacities = 0.6 + 0.35 * scene.opacities
    assert brute.render(*scene.params(), *scene.camera())["stopped"].float().mean() > 0.5
    _assert_close(_images_and_grads(render_cpu, scene), _bruteforce(scene), 1e-10)


@pytest.mark.parametrize("tile_size", [8, 16])
def test_gaussian_straddling_tiles_matches_bruteforce(tile_size: int) -> None:
    scene = single_gaussian(pixel=(15.5, 15.5), depth=2.0, sigma_px=2.5, opacity=0.8, width=32, height=32)
    _assert_close(_images_and_grads(render_cpu, scene, tile_size=tile_size), _bruteforce(scene), 1e-10)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_the_torch_backend(dtype: torch.dtype) -> None:
    """Images, gradients of all six inputs and of means2d, radii and means2d, on a bigger scene."""
    scene = random_scene(300, seed=12, width=61, height=47, scale=0.25, dtype=dtype)
    got = _images_and_grads(render_cpu, scene)
    _assert_close(got, _images_and_grads(render_torch, scene), TOL[dtype])
    cpu, ref = (r(*scene.params(), *scene.camera()) for r in (render_cpu, render_torch))
    # Two implementations: means2d to rounding (observed: under 1 ULP of the largest, on AMD EPYC and Intel
    # Xeon alike; not bit for bit on the Xeon), radii (ceil of a float) equal but where one lands on an integer.
    assert_within_ulps(cpu.means2d, ref.means2d, ulps=4, what="means2d")
    assert_rounded_alike(cpu.radii, ref.radii, at_most=3, what="radii")  # 1 % of 300


def test_float32_matches_float64_reference() -> None:
    s64 = random_scene(40, seed=2, width=40, height=36, scale=0.2)
    s32 = random_scene(40, seed=2, width=40, height=36, scale=0.2, dtype=torch.float32)
    ref = _bruteforce(s64)
    images, grads = _images_and_grads(render_cpu, s32)
    for k in ("rgb", "alpha"):
        assert (images[k].double() - ref[0][k]).abs().max() < 1e-5, k
    assert (images["depth"].double() - ref[0]["depth"]).abs().max() < 1e-4  # depth ~3
    for name, g, r in zip((*NAMES, "means2d"), grads, ref[1]):
        assert ((g.double() - r).abs().max() / r.abs().max()).item() < 1e-5, name


def test_gradcheck_render_cpu() -> None:
    scene = random_scene(6, seed=5, width=12, height=10, focal=15.0, scale=0.2)
    inputs = tuple(t.detach().clone().requires_grad_(True) for t in _inputs(scene))

    def render(*params: torch.Tensor) -> torch.Tensor:
        out = render_cpu(*params[:5], scene.K, scene.world_to_cam, scene.width, scene.height, params[5], tile_size=8)
        return torch.cat([out.rgb.flatten(), out.alpha.flatten(), out.depth.flatten()])

    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_thread_count_and_tile_size_do_not_change_the_result() -> None:
    """Bit for bit: images and gradients over 1, 2 and 3 threads; images over tile sizes 8 and 16
    (gradients there agree to rounding: the per-tile partial sums differ)."""
    scene = random_scene(3000, seed=21, width=96, height=80, scale=0.15, dtype=torch.float32)
    threads = torch.get_num_threads()
    try:
        results = []
        for t in (1, 2, 3):
            torch.set_num_threads(t)
            results.append(_images_and_grads(render_cpu, scene))
    finally:
        torch.set_num_threads(threads)
    for images, grads in results[1:]:
        assert all(torch.equal(images[k], results[0][0][k]) for k in OUTPUTS)
        assert all(torch.equal(g, r) for g, r in zip(grads, results[0][1]))
    images8, grads8 = _images_and_grads(render_cpu, scene, tile_size=8)
    assert all(torch.equal(images8[k], results[0][0][k]) for k in OUTPUTS)
    _assert_close((images8, grads8), results[0], 1e-5)


def test_auto_picks_the_compiled_backend_for_cpu_float_tensors() -> None:
    assert resolve_backend("auto", torch.zeros(1, 3)) == "cpu"
    assert resolve_backend("auto", torch.zeros(1, 3, dtype=torch.float64)) == "cpu"
    assert resolve_backend("auto", torch.zeros(1, 3, dtype=torch.bfloat16)) == "torch"
    scene = random_scene(20, seed=4, dtype=torch.float32)
    auto = render_gaussians(*scene.params(), *scene.camera())
    assert torch.equal(auto.rgb, render_cpu(*scene.params(), *scene.camera()).rgb)


def test_grad2d_is_dl_dmeans2d() -> None:
    scene = random_scene(12, seed=8).requires_grad_()
    out = render_gaussians(*scene.params(), *scene.camera(), backend="cpu")
    (out.rgb.sum() + out.alpha.sum()).backward()
    ref = render_torch(*[p.detach().requires_grad_() for p in scene.params()], *scene.camera())
    (ref.rgb.sum() + ref.alpha.sum()).backward()
    assert torch.allclose(out.grad2d(), ref.grad2d(), rtol=0, atol=1e-12)
    assert torch.allclose(out.grad2d_norm(), ref.grad2d_norm(), rtol=0, atol=1e-12)


def test_work_counts() -> None:
    """One opaque-enough Gaussian alone: it is evaluated on its box and contributes where alpha >= 1/255."""
    scene = single_gaussian(pixel=(11.5, 9.5), depth=2.0, sigma_px=1.5, opacity=0.9)
    evaluations, contributions = work_counts(*scene.params(), *scene.camera())
    out = render_cpu(*scene.params(), *scene.camera())
    assert 0 < contributions == int((out.alpha > 0).sum()) <= evaluations <= (2 * int(out.radii[0]) + 1) ** 2


def test_invalid_tile_size_is_rejected() -> None:
    scene = random_scene(3, seed=0)
    with pytest.raises(RuntimeError, match="tile_size must be 8 or 16"):
        render_cpu(*scene.params(), *scene.camera(), tile_size=4)
