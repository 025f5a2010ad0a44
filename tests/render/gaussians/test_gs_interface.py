"""``render_gaussians``: backend choice, input checks, conventions, dtype and memory behaviour."""

from __future__ import annotations

import pytest
import torch
from gs_scenes import intrinsics, random_scene, single_gaussian

from avatar.render.gaussians import available_backends, render_gaussians
from avatar.render.gaussians.backend_gsplat import gsplat_available
from avatar.render.gaussians.backend_torch import render_torch
from avatar.render.gaussians.render import resolve_backend
from pipeline.monitor import ResourceMonitor


def test_torch_backend_is_always_available_and_auto_picks_a_cpu_backend_on_cpu() -> None:
    assert available_backends()[0] == "torch"
    compiled = "cpu" if "cpu" in available_backends() else "torch"
    assert resolve_backend("auto", torch.zeros(1, 3)) == compiled
    assert resolve_backend("auto", torch.zeros(1, 3, dtype=torch.float16)) == "torch"
    assert resolve_backend("torch", torch.zeros(1, 3)) == "torch"


def test_unknown_backend_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown Gaussian rasterizer backend"):
        resolve_backend("optix", torch.zeros(1, 3))


@pytest.mark.skipif(gsplat_available(), reason="gsplat is available here")
def test_gsplat_without_cuda_or_package_says_how_to_fix() -> None:
    with pytest.raises(RuntimeError, match="pip install gsplat"):
        resolve_backend("gsplat", torch.zeros(1, 3))


def test_shapes_are_checked() -> None:
    scene = random_scene(3, seed=0)
    with pytest.raises(ValueError, match=r"quats has shape \(3, 3\), expected \(3, 4\)"):
        render_gaussians(scene.means, scene.quats[:, :3], scene.scales, scene.opacities, scene.colors, *scene.camera())


def test_output_shapes_and_types() -> None:
    scene = random_scene(7, seed=1, dtype=torch.float32)
    out = render_gaussians(*scene.params(), *scene.camera())
    assert out.rgb.shape == (scene.height, scene.width, 3)
    assert out.alpha.shape == out.depth.shape == (scene.height, scene.width)
    assert out.means2d.shape == (7, 2) and out.rgb.dtype == torch.float32
    assert out.radii.shape == (7,) and out.radii.dtype == torch.int32
    assert (out.grad2d_norm() == 0).all()  # no backward yet


def test_opencv_pixel_centres() -> None:
    """A Gaussian whose mean projects to (x, y) = (7, 5) peaks at pixel (row 5, col 7), symmetrically."""
    scene = single_gaussian(pixel=(7.0, 5.0), depth=2.0, sigma_px=1.5, opacity=0.9)
    out = render_gaussians(*scene.params(), *scene.camera())
    assert out.means2d[0].tolist() == pytest.approx([7.0, 5.0], abs=1e-12)
    assert out.alpha.argmax().item() == 5 * scene.width + 7
    assert out.alpha[5, 6].item() == pytest.approx(out.alpha[5, 8].item(), abs=1e-12)
    assert out.alpha[4, 7].item() == pytest.approx(out.alpha[6, 7].item(), abs=1e-12)
    assert out.depth[5, 7].item() == pytest.approx(2.0 * out.alpha[5, 7].item(), abs=1e-12)


def test_principal_point_maps_to_the_optical_axis() -> None:
    k = intrinsics(24, 20)
    scene = single_gaussian(pixel=(float(k[0, 2]), float(k[1, 2])), depth=3.0, sigma_px=1.0, opacity=0.5)
    out = render_gaussians(*scene.params(), *scene.camera())
    assert out.means2d[0].tolist() == pytest.approx([11.5, 9.5], abs=1e-12)
    assert scene.means[0, :2].abs().max() < 1e-12


def test_float32_agrees_with_float64_and_tile_size_does_not_matter() -> None:
    s64 = random_scene(40, seed=2, width=40, height=36, scale=0.2)
    s32 = random_scene(40, seed=2, width=40, height=36, scale=0.2, dtype=torch.float32)
    ref = render_torch(*s64.params(), *s64.camera())
    for tile_size in (4, 16):
        out = render_torch(*s32.params(), *s32.camera(), tile_size=tile_size)
        assert (out.rgb.double() - ref.rgb).abs().max() < 1e-5
        assert (out.alpha.double() - ref.alpha).abs().max() < 1e-5
        assert (out.depth.double() - ref.depth).abs().max() < 1e-4  # depth ~3


def _peak_rss_delta(fn) -> float:
    """Peak increase of the process RSS (bytes) while ``fn`` runs, sampled every 2 ms."""
    with ResourceMonitor(interval_s=0.002) as monitor:
        fn()
    return monitor.usage.rss_growth_mb * 2**20


@pytest.mark.slow
def test_512px_200k_gaussians_fit_in_bounded_memory() -> None:
    """An (H*W, N) float32 tensor alone would be 210 GB; the whole forward + backward stays < 2 GiB."""
    n, size = 200_000, 512
    g = torch.Generator().manual_seed(0)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    params = [
        direction * 0.1 + torch.tensor([0.0, 0.0, 0.7]),
        torch.randn(n, 4, generator=g),
        0.001 + 0.002 * torch.rand(n, 3, generator=g),
        torch.rand(n, generator=g),
        torch.rand(n, 3, generator=g),
    ]
    for p in params:
        p.requires_grad_(True)
    k = torch.tensor([[2.0 * size, 0.0, (size - 1) / 2], [0.0, 2.0 * size, (size - 1) / 2], [0.0, 0.0, 1.0]])

    def run() -> None:
        out = render_gaussians(*params, k, torch.eye(4), size, size, torch.zeros(3), backend="torch")
        (out.rgb.sum() + out.depth.sum()).backward()
        assert torch.isfinite(out.rgb).all() and (out.radii > 0).sum() > 0.9 * n

    assert _peak_rss_delta(run) < 2 * 2**30
    assert all(torch.isfinite(p.grad).all() for p in params)
