"""The torch rasterizer against the brute-force renderer (float64, tight tolerances) and gradcheck.

Tolerances (float64): images to 1e-10 absolute; gradients to 1e-9 relative to the largest
reference entry of each input. Both implementations compute the same maths in a different
order, so the observed differences are ~1e-14.
"""

from __future__ import annotations

import gs_bruteforce as brute
import pytest
import torch
from gs_scenes import Scene, random_scene, single_gaussian

from avatar.render.gaussians.backend_torch import render_torch
from avatar.render.gaussians.compositing import CompositeSettings, composite
from avatar.render.gaussians.projection import ALPHA_MIN, project_gaussians
from avatar.render.gaussians.tiling import build_tile_lists

IMAGE_ATOL = 1e-10
GRAD_RTOL = 1e-9
OUTPUTS = ("rgb", "alpha", "depth")


def _loss_weights(scene: Scene, seed: int = 7) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = {
        "rgb": (scene.height, scene.width, 3),
        "alpha": (scene.height, scene.width),
        "depth": (scene.height, scene.width),
    }
    return {k: torch.rand(shape, generator=g, dtype=scene.means.dtype) for k, shape in shapes.items()}


def _loss(images: dict[str, torch.Tensor], weights: dict[str, torch.Tensor]) -> torch.Tensor:
    return sum((images[k] * weights[k]).sum() for k in OUTPUTS)


def _torch_images(scene: Scene, **kwargs) -> dict[str, torch.Tensor]:
    out = render_torch(*scene.params(), *scene.camera(), **kwargs)
    return {"rgb": out.rgb, "alpha": out.alpha, "depth": out.depth}


def _assert_images_match(scene: Scene, **kwargs) -> None:
    ref = brute.render(*scene.params(), *scene.camera())
    got = _torch_images(scene, **kwargs)
    for k in OUTPUTS:
        err = (got[k] - ref[k]).abs().max().item()
        assert err <= IMAGE_ATOL, f"{k}: max abs error {err:.3e}"


def _assert_gradients_match(scene: Scene, **kwargs) -> None:
    scene.requires_grad_()
    weights = _loss_weights(scene)
    ref = torch.autograd.grad(_loss(brute.render(*scene.params(), *scene.camera()), weights), scene.params())
    got = torch.autograd.grad(_loss(_torch_images(scene, **kwargs), weights), scene.params())
    for name, g, r in zip(("means", "quats", "scales", "opacities", "colors"), got, ref):
        assert torch.isfinite(g).all(), name
        err = ((g - r).abs().max() / r.abs().max().clamp_min(1e-30)).item()
        assert err <= GRAD_RTOL, f"d/d{name}: relative error {err:.3e}"


@pytest.mark.parametrize("tile_size", [4, 16])
@pytest.mark.parametrize("seed,n", [(0, 10), (1, 20), (2, 30)])
def test_images_match_bruteforce(seed: int, n: int, tile_size: int) -> None:
    _assert_images_match(random_scene(n, seed), tile_size=tile_size)


@pytest.mark.parametrize("seed,n", [(0, 10), (1, 20), (2, 30)])
def test_gradients_match_bruteforce(seed: int, n: int) -> None:
    _assert_gradients_match(random_scene(n, seed))


def test_gaussian_straddling_four_tiles_matches_bruteforce() -> None:
    # Pixel centres 15 and 16 lie on either side of the 16-pixel tile border at x = y = 15.5.
    scene = single_gaussian(pixel=(15.5, 15.5), depth=2.0, sigma_px=2.5, opacity=0.8, width=32, height=32)
    proj = project_gaussians(*scene.params()[:4], scene.K, scene.world_to_cam, 32, 32, 0.01, 100.0)
    lists = build_tile_lists(proj.box, proj.depths, proj.visible, 32, 32, tile_size=16)
    assert lists.counts.tolist() == [1, 1, 1, 1]
    _assert_images_match(scene, tile_size=16)
    _assert_gradients_match(scene, tile_size=16)


def test_early_stop_matches_bruteforce() -> None:
    """A deep stack of large, fairly opaque Gaussians: most pixels stop before the end of the list."""
    scene = random_scene(40, seed=3, scale=1.0)
    scene.opacities = 0.6 + 0.35 * scene.opacities
    ref = brute.render(*scene.params(), *scene.camera())
    assert ref["stopped"].float().mean() > 0.5
    _assert_images_match(scene)
    _assert_gradients_match(scene)


@pytest.mark.parametrize("round_len,max_elements", [(1, 1), (3, 100), (5, 10_000)])
def test_step_sizes_do_not_change_the_result(round_len: int, max_elements: int) -> None:
    """Tiny steps split every tile list across many steps (transmittance carried forward, suffix
    sums carried backward): same images and gradients as the brute force."""
    scene = random_scene(12, seed=4, width=16, height=12, scale=0.3)
    settings = CompositeSettings(round_len=round_len, max_chunk_elements=max_elements)
    _assert_images_match(scene, tile_size=8, settings=settings)
    _assert_gradients_match(scene, tile_size=8, settings=settings)


def test_gradcheck_render_torch() -> None:
    scene = random_scene(6, seed=5, width=12, height=10, focal=15.0, scale=0.2).requires_grad_()

    def render(*params: torch.Tensor) -> torch.Tensor:
        out = render_torch(*params, *scene.camera(), tile_size=4)
        return torch.cat([out.rgb.flatten(), out.alpha.flatten(), out.depth.flatten()])

    assert torch.autograd.gradcheck(render, tuple(scene.params()), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gradcheck_compositing_function() -> None:
    """gradcheck of the custom autograd.Function alone, on its (N, 6 + C) table input."""
    scene = random_scene(6, seed=6, width=9, height=7, focal=12.0, scale=0.25)
    proj = project_gaussians(*scene.params()[:4], scene.K, scene.world_to_cam, 9, 7, 0.01, 100.0)
    lists = build_tile_lists(proj.box, proj.depths, proj.visible, 9, 7, tile_size=4)
    table = (
        torch.cat(
            [
                proj.means2d,
                proj.conics,
                scene.opacities.clamp_min(ALPHA_MIN).log()[:, None],
                scene.colors,
                proj.depths[:, None],
            ],
            -1,
        )
        .detach()
        .requires_grad_()
    )
    settings = CompositeSettings(round_len=2, max_chunk_elements=64)

    def run(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return composite(t, lists, 9, 7, settings)

    assert torch.autograd.gradcheck(run, (table,), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_means2d_gradient_matches_bruteforce() -> None:
    """grad2d is dL/d(projected mean): the brute force composited from 2D leaf means agrees, it is
    non-zero for visible Gaussians and zero for culled ones (one behind the camera, one off-screen)."""
    scene = random_scene(12, seed=8)
    culled = random_scene(2, seed=9)
    culled.means = torch.tensor([[0.0, 0.0, -6.0], [40.0, 0.0, 0.0]], dtype=torch.float64)  # behind, off-screen
    scene = scene.cat(culled).requires_grad_()
    weights = _loss_weights(scene)
    out = render_torch(*scene.params(), *scene.camera())
    _loss({"rgb": out.rgb, "alpha": out.alpha, "depth": out.depth}, weights).backward()

    means2d, cov2d, z = brute.project(*scene.params()[:3], scene.K, scene.world_to_cam, scene.width, scene.height)
    leaf = means2d.detach().requires_grad_()
    ref_images = brute.composite(
        leaf,
        cov2d.detach(),
        z.detach(),
        scene.opacities.detach(),
        scene.colors.detach(),
        scene.width,
        scene.height,
        scene.background,
        (z >= 0.01) & (z <= 100.0),
    )
    (ref,) = torch.autograd.grad(_loss(ref_images, weights), leaf)

    grad2d = out.grad2d()
    assert torch.equal(grad2d, out.means2d.grad)
    assert ((grad2d - ref).abs().max() / ref.abs().max()).item() <= GRAD_RTOL
    visible = out.radii > 0
    assert visible[:12].all() and not visible[12:].any()
    assert (out.grad2d_norm()[:12] > 0).all()
    assert (out.grad2d_norm()[12:] == 0).all()
