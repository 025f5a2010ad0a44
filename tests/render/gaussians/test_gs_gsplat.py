"""gsplat against the torch backend on the same Gaussians (needs CUDA and gsplat; skipped otherwise).

Scene: 2000 random Gaussians, 128 x 128, float32 on the GPU, opacities in [0.05, 0.95] so that
neither backend's alpha clamp (torch 0.99, gsplat 0.999) is reached. Tolerances:

* images: max abs difference 2e-3 on rgb and alpha, 2e-3 relative to the largest depth on depth;
* gradients w.r.t. means, colors, opacities and the 2D means: ``||g_torch - g_gsplat|| <= 2e-2 ||g_gsplat||``
  (2-norm over all entries; both are float32 sums in different orders).

The equivalence needs gsplat >= 1.5, whose opacity-aware culling box is the torch backend's;
gsplat 1.4 culls at 3 sigma and drops faint tails that both 3DGS and the torch backend keep.
"""

from __future__ import annotations

import importlib.metadata

import pytest
import torch

from avatar.render.gaussians import render_gaussians
from avatar.render.gaussians.backend_gsplat import gsplat_available

pytestmark = pytest.mark.cuda


def _gsplat_at_least(major: int, minor: int) -> bool:
    version = importlib.metadata.version("gsplat").split(".")
    return (int(version[0]), int(version[1])) >= (major, minor)


requires_gsplat = pytest.mark.skipif(
    not gsplat_available() or not _gsplat_at_least(1, 5), reason="needs CUDA and gsplat >= 1.5"
)
SIZE, N = 128, 2000


def _scene(seed: int = 0) -> tuple[list[torch.Tensor], tuple]:
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 2.0 * torch.rand(N, generator=g)
    xy = (torch.rand(N, 2, generator=g) - 0.5) * 1.2 * z[:, None]
    params = [
        torch.cat([xy, z[:, None]], -1),
        torch.randn(N, 4, generator=g),
        0.005 + 0.025 * torch.rand(N, 3, generator=g),
        0.05 + 0.9 * torch.rand(N, generator=g),
        torch.rand(N, 3, generator=g),
    ]
    k = torch.tensor([[SIZE * 0.8, 0.0, (SIZE - 1) / 2], [0.0, SIZE * 0.8, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
    camera = (k.cuda(), torch.eye(4).cuda(), SIZE, SIZE, torch.tensor([0.1, 0.2, 0.3]).cuda())
    return [p.cuda().requires_grad_(True) for p in params], camera


def _render(backend: str):
    params, camera = _scene()
    out = render_gaussians(*params, *camera, backend=backend)
    g = torch.Generator(device="cuda").manual_seed(1)
    loss = (out.rgb * torch.rand(out.rgb.shape, generator=g, device="cuda")).sum() + out.alpha.sum()
    loss.backward()
    return out, params


@requires_gsplat
def test_gsplat_and_torch_render_the_same_image() -> None:
    ours, _ = _render("torch")
    theirs, _ = _render("gsplat")
    assert (ours.rgb - theirs.rgb).abs().max() <= 2e-3
    assert (ours.alpha - theirs.alpha).abs().max() <= 2e-3
    assert (ours.depth - theirs.depth).abs().max() <= 2e-3 * theirs.depth.abs().max()
    assert (ours.means2d - theirs.means2d).abs().max() <= 1e-3  # both in OpenCV pixel coordinates
    assert ((ours.radii > 0) == (theirs.radii > 0)).float().mean() > 0.99


@requires_gsplat
def test_gsplat_and_torch_give_the_same_gradients() -> None:
    ours, p_ours = _render("torch")
    theirs, p_theirs = _render("gsplat")
    pairs = {
        "means": (p_ours[0].grad, p_theirs[0].grad),
        "opacities": (p_ours[3].grad, p_theirs[3].grad),
        "colors": (p_ours[4].grad, p_theirs[4].grad),
        "means2d": (ours.grad2d(), theirs.grad2d()),
    }
    for name, (a, b) in pairs.items():
        rel = ((a - b).norm() / b.norm()).item()
        assert rel <= 2e-2, f"{name}: relative error {rel:.3e}"
