"""The reference backend: a tiled EWA rasterizer in pure PyTorch (any device, any float dtype)."""

from __future__ import annotations

import torch
from torch import Tensor

from .compositing import CompositeSettings, composite
from .output import RenderOutput
from .projection import ALPHA_MIN, project_gaussians
from .tiling import build_tile_lists

#: Tile side in pixels. It changes speed only, never the image (see ``projection.alpha_extent``);
#: 4 is the fastest on a CPU for avatar-like Gaussians (``benchmarks/bench_rasterizer.py``).
DEFAULT_TILE_SIZE = 4


def render_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    width: int,
    height: int,
    background: Tensor,
    near: float = 0.01,
    far: float = 100.0,
    tile_size: int = DEFAULT_TILE_SIZE,
    settings: CompositeSettings = CompositeSettings(),
) -> RenderOutput:
    """Render N Gaussians with the pure-PyTorch tiled rasterizer (arguments as ``render_gaussians``).

    ``tile_size`` and ``settings`` trade speed and memory; the image does not depend on them.
    """
    proj = project_gaussians(means, quats, scales, opacities, K, world_to_cam, width, height, near, far)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    lists = build_tile_lists(proj.box, proj.depths, proj.visible, width, height, tile_size)
    log_opacity = opacities.clamp_min(ALPHA_MIN).log()  # culled below ALPHA_MIN: never read
    table = torch.cat([means2d, proj.conics, log_opacity[:, None], colors, proj.depths[:, None]], -1)
    feat, alpha = composite(table, lists, width, height, settings)
    rgb = feat[..., :3] + (1.0 - alpha)[..., None] * background.to(feat.dtype)
    return RenderOutput(
        rgb=rgb, alpha=alpha, depth=feat[..., 3], means2d=means2d, radii=proj.radii, grad_holder=means2d
    )
