"""The gsplat adapter against the project's backends: on the CPU through gsplat's PyTorch reference
(``gsplat_reference.py``), and through its CUDA kernels where a GPU is present (``make test-gpu``).

``avatar.render.gaussians.backend_gsplat.render_gsplat`` runs unchanged; on the CPU only gsplat's CUDA kernels
are swapped for its PyTorch reference. The scenes are CPU tensors (with CUDA the adapter copies them to the
GPU and back). Against the project's compiled ``cpu`` backend (the torch backend where
it is not built), float32, opacities below 0.95 (neither alpha clamp reached):

* rgb, alpha and depth within 1e-5; ``means2d`` of the drawn Gaussians within 1e-4 px (gsplat projects in
  float32, the project in float64); radii equal, except a faint Gaussian whose box holds no pixel centre:
  gsplat keeps it (drawing nothing), the project's backends cull it;
* gradients of means, quats, scales, opacities, colors, background and the 2D means within 1e-5 of the
  largest entry (+1e-6), as the compiled backend against the torch backend; 1e-4 through the CUDA kernels
  (fast math and atomics; measured 2.6e-5 to 6.7e-5 on an H200).

The extremes run through gsplat too (``test_gs_extremes.py``). The documented differences (alpha clamp,
depth ties) are asserted here as such, so that a change of either side shows.
"""

from __future__ import annotations

import pytest
import torch
from gs_scenes import Scene, random_scene, single_gaussian
from gsplat_reference import isect_tiles

from avatar.render.gaussians import RenderOutput, render_gaussians
from avatar.render.gaussians.extension import cpu_extension_available

pytestmark = pytest.mark.usefixtures("gsplat_kernels")
F32 = torch.float32
#: gradient tolerance relative to the largest entry: gsplat's CUDA kernels use fast math and atomics
#: (2.6e-5 to 6.7e-5 measured on an H200)
GRAD_TOL = {"reference": 1e-5, "cuda": 1e-4}
PROJECT = "cpu" if cpu_extension_available() else "torch"


def _backward(scene: Scene, backend: str) -> tuple[RenderOutput, list[torch.Tensor]]:
    params = [p.detach().clone().requires_grad_(True) for p in (*scene.params(), scene.background)]
    out = render_gaussians(
        *params[:5], scene.K, scene.world_to_cam, scene.width, scene.height, params[5], backend=backend
    )
    g = torch.Generator().manual_seed(3)
    weights = [torch.rand(x.shape, generator=g) for x in (out.rgb, out.alpha, out.depth)]
    sum(w.mul(x).sum() for w, x in zip(weights, (out.rgb, out.alpha, out.depth))).backward()
    return out, [p.grad for p in params]


def _assert_same(scene: Scene, kernels: str) -> None:
    theirs, their_grads = _backward(scene, "gsplat")
    ours, our_grads = _backward(scene, PROJECT)
    for name in ("rgb", "alpha", "depth"):
        diff = (getattr(theirs, name) - getattr(ours, name)).abs().max().item()
        assert diff <= 1e-5, f"{name}: {diff:.2e}"
    drawn = ours.radii > 0  # a culled Gaussian's 2D mean is undefined (gsplat leaves it unwritten)
    assert (theirs.means2d[drawn] - ours.means2d[drawn]).abs().max() <= 1e-4
    # gsplat keeps a Gaussian whose opacity-aware box holds no pixel centre (radius 1, drawing nothing);
    # the project's backends cull it (radius 0)
    differ = theirs.radii != ours.radii
    assert (ours.radii[differ] == 0).all() and (their_grads[4][differ] == 0).all()
    names = ("means", "quats", "scales", "opacities", "colors", "background", "means2d")
    for name, a, b in zip(names, [*their_grads, theirs.grad2d()], [*our_grads, ours.grad2d()]):
        tol = GRAD_TOL[kernels] * b.abs().max() + 1e-6
        assert ((a - b).abs() <= tol).all(), f"d/d{name}: {(a - b).abs().max():.2e} > {tol:.2e}"


@pytest.mark.parametrize("seed,n", [(0, 10), (1, 60), (2, 200)])
def test_random_scenes_match_the_project_backend(seed: int, n: int, gsplat_kernels: str) -> None:
    _assert_same(random_scene(n, seed, dtype=F32, max_opacity=0.95), gsplat_kernels)


def test_a_larger_scene_over_many_tiles(gsplat_kernels: str) -> None:
    """Image sizes that are not multiples of gsplat's 16-px tiles, a principal point off the centre."""
    scene = random_scene(1500, 4, width=70, height=45, focal=60.0, dtype=F32, max_opacity=0.95, scale=0.05)
    scene.K[0, 2], scene.K[1, 2] = 30.25, 25.5
    _assert_same(scene, gsplat_kernels)


@pytest.mark.parametrize("pixel", [(11.0, 9.0), (3.5, 2.25), (0.0, 0.0)])
def test_pixel_centres_and_principal_point(pixel: tuple[float, float], gsplat_kernels: str) -> None:
    """A small Gaussian centred on ``pixel`` (OpenCV coordinates): the same 2D mean and the same image."""
    scene = single_gaussian(pixel=pixel, depth=2.0, sigma_px=1.3, opacity=0.8, dtype=F32)
    theirs = render_gaussians(*scene.params(), *scene.camera(), backend="gsplat")
    assert torch.allclose(theirs.means2d[0], torch.tensor(pixel), atol=1e-4)
    _assert_same(scene, gsplat_kernels)


def test_alpha_clamp_is_a_documented_difference() -> None:
    """An opaque Gaussian on a pixel: gsplat clamps alpha at 0.999, the project's backends at 0.99."""
    scene = single_gaussian(pixel=(11.0, 9.0), depth=2.0, sigma_px=1.0, opacity=1.0, dtype=F32)
    theirs = render_gaussians(*scene.params(), *scene.camera(), backend="gsplat")
    ours = render_gaussians(*scene.params(), *scene.camera(), backend=PROJECT)
    assert theirs.alpha[9, 11].item() == pytest.approx(0.999, abs=1e-6)
    assert ours.alpha[9, 11].item() == pytest.approx(0.99, abs=1e-6)


def test_depth_ties_composite_in_index_order_when_float32_depths_are_equal() -> None:
    """Two overlapping Gaussians at the same world depth composite first-index-first in both, as long as
    float32 gives both the same camera depth (gsplat computes it in float32, the project in float64)."""
    scene = single_gaussian(pixel=(11.0, 9.0), depth=2.0, sigma_px=2.0, opacity=0.7, dtype=F32)
    twin = single_gaussian(pixel=(11.0, 9.0), depth=2.0, sigma_px=2.0, opacity=0.7, dtype=F32)
    twin.colors = torch.tensor([[0.0, 1.0, 0.0]])
    both = scene.cat(twin)
    theirs = render_gaussians(*both.params(), *both.camera(), backend="gsplat")
    ours = render_gaussians(*both.params(), *both.camera(), backend=PROJECT)
    assert torch.allclose(theirs.rgb, ours.rgb, atol=1e-5)


def test_isect_tiles_is_gsplats_reference() -> None:
    """The vectorised tile intersection gives gsplat's ``_isect_tiles`` keys and ids (two images, culled
    Gaussians, boxes past every border)."""
    from gsplat.cuda._torch_impl import _isect_tiles

    g = torch.Generator().manual_seed(0)
    means2d = torch.rand(2, 150, 2, generator=g) * 70 - 5
    radii = (torch.rand(2, 150, 2, generator=g) * 14).int()
    radii[:, :20] = 0
    depths = torch.rand(2, 150, generator=g)
    ours = isect_tiles(means2d, radii, depths, 16, 4, 3, sort=False)
    theirs = _isect_tiles(means2d, radii, depths, 16, 4, 3, sort=False)
    for a, b in zip(ours, theirs):
        assert torch.equal(a.long(), b.long())
