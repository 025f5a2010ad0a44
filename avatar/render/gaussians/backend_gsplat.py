"""Adapter to gsplat's CUDA rasterizer (``gsplat.rasterization``, gsplat >= 1.4 API).

Pixel convention: gsplat (like the reference 3DGS code) puts pixel ``(i, j)``'s centre at
``(j + 0.5, i + 0.5)``, this project at ``(j, i)`` (OpenCV). The adapter therefore shifts the
principal point by +0.5 before calling gsplat and its returned ``means2d`` by -0.5.

Known differences from the torch backend: gsplat clamps alpha at 0.999 (torch: 0.99, as 3DGS),
so the two differ where ``opacity * G > 0.99``; it stops at ``T <= 1e-4`` (torch: ``< 1e-4``);
gsplat < 1.5 culls at 3 sigma instead of the opacity-aware extent and drops faint tails.
Only the documented ``rasterization`` signature is used; this adapter has not run here (no
CUDA), ``tests/render/gaussians/test_gs_gsplat.py`` checks it wherever a GPU is present.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from .output import RenderOutput


@functools.cache
def gsplat_available() -> bool:
    """True when ``import gsplat`` works and a CUDA device is present."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # an install without its CUDA extension fails in many ways
        return False
    return True


def render_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                  K: Tensor, world_to_cam: Tensor, width: int, height: int, background: Tensor,
                  near: float = 0.01, far: float = 100.0) -> RenderOutput:
    """Render N Gaussians with ``gsplat.rasterization`` (float32 CUDA tensors; arguments as
    ``render_gaussians``)."""
    from gsplat import rasterization

    k_gsplat = K.detach().clone().to(means)
    k_gsplat[:2, 2] += 0.5
    colors_depth, alphas, meta = rasterization(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
        viewmats=world_to_cam.detach().to(means)[None], Ks=k_gsplat[None], width=width, height=height,
        near_plane=near, far_plane=far, backgrounds=background.to(means)[None],
        render_mode="RGB+D", packed=False, rasterize_mode="classic",
    )
    holder = meta["means2d"]  # (1, N, 2), gsplat's pixel frame
    if holder.requires_grad:
        holder.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5: per-axis radii (N, 2)
        radii = radii.amax(-1)
    return RenderOutput(rgb=colors_depth[0, ..., :3], alpha=alphas[0, ..., 0], depth=colors_depth[0, ..., 3],
                        means2d=holder[0] - 0.5, radii=radii.to(torch.int32), grad_holder=holder)
