"""The compiled CPU backend: the torch backend's maths as C++/OpenMP operators (``csrc/rasterizer_cpu.cpp``).

Three steps, as in the 3DGS and gsplat CUDA code: ``_Project`` (EWA projection, its own
backward), tile binning (not differentiable) and ``_Rasterize`` (front-to-back compositing; its
backward replays each pixel's list from the back, dividing the transmittance back, and stores
nothing per (Gaussian, pixel)). Float32 and float64. Images and gradients do not depend on the
thread count (``torch.get_num_threads()``), nor images on the tile size, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .extension import unavailable_reason
from .output import RenderOutput

#: Tile side in pixels (speed only; ``benchmarks/bench_rasterizer.py --tile-sizes`` measures it).
DEFAULT_TILE_SIZE = 16
#: Dtypes the operators are compiled for.
DTYPES = (torch.float32, torch.float64)


def _ops():  # the torch.ops namespace object
    """The compiled operators, built and loaded on first use."""
    reason = unavailable_reason()
    if reason is not None:
        raise RuntimeError(f"the compiled CPU rasterizer is unavailable: {reason}")
    return torch.ops.interactavatar_gs


@dataclass(frozen=True)
class _Camera:
    """Camera arguments of the projection operators (K and world_to_cam as float64 (3, 3), (4, 4))."""

    K: Tensor
    world_to_cam: Tensor
    width: int
    height: int
    near: float
    far: float

    def args(self) -> tuple:
        return self.K, self.world_to_cam, self.width, self.height, self.near, self.far


@dataclass(frozen=True)
class TileBins:
    """Depth-sorted per-tile Gaussian lists of a ``tile_size`` grid (``bin_tiles``).

    Attributes:
        order: (V,) int32 the visible Gaussians, front to back (depth, then index).
        ids: (P,) int32 Gaussian (its rank in ``order``) of every (tile, Gaussian) pair, grouped by
            tile, front to back.
        tile_offsets: (T + 1,) int64 start of each tile's list in ``ids``.
        slots: (P,) int32 the pair's row in the backward's per-pair gradients, grouped by Gaussian
            (tile order within a Gaussian).
        gauss_offsets: (N + 1,) int64 start of each Gaussian's slots.
        box: (N, 4) int32 inclusive pixel box ``(x0, y0, x1, y1)`` per Gaussian.
        tile_size, width, height: the grid.
    """

    order: Tensor
    ids: Tensor
    tile_offsets: Tensor
    slots: Tensor
    gauss_offsets: Tensor
    box: Tensor
    tile_size: int
    width: int
    height: int

    def raster_args(self) -> tuple:
        return self.box, self.order, self.ids, self.tile_offsets

    def grid_args(self) -> tuple:
        return self.width, self.height, self.tile_size


class _Project(torch.autograd.Function):
    """(means (N, 3), quats (N, 4), scales (N, 3), opacities (N,)) -> means2d (N, 2), conics (N, 3),
    depths (N,) (differentiable) and radii (N,) int32, box (N, 4) int32, visible (N,) bool."""

    @staticmethod
    def forward(
        ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: _Camera
    ) -> tuple[Tensor, ...]:
        out = _ops().project_forward(means, quats, scales, opacities, *camera.args(), torch.get_num_threads())
        ctx.save_for_backward(means, quats, scales)
        ctx.camera = camera
        ctx.mark_non_differentiable(*out[3:])
        return out

    @staticmethod
    @once_differentiable
    def backward(
        ctx: Any, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor, *_: Tensor
    ) -> tuple[Tensor | None, ...]:
        means, quats, scales = ctx.saved_tensors
        grads = _ops().project_backward(
            means, quats, scales, *ctx.camera.args(), g_means2d, g_conics, g_depths, torch.get_num_threads()
        )
        return *grads, None, None


class _Rasterize(torch.autograd.Function):
    """(means2d (N, 2), conics (N, 3), opacities (N,), colors (N, 3), depths (N,), background (3,))
    -> rgb (H, W, 3), alpha (H, W), depth (H, W)."""

    @staticmethod
    def forward(
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        depths: Tensor,
        background: Tensor,
        bins: TileBins,
    ) -> tuple[Tensor, Tensor, Tensor]:
        rgb, alpha, depth, t_final, last, kept_rows = _ops().rasterize_forward(
            means2d,
            conics,
            opacities,
            colors,
            depths,
            background,
            *bins.raster_args(),
            *bins.grid_args(),
            torch.get_num_threads(),
        )
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, background, alpha, t_final, last, kept_rows)
        ctx.bins = bins
        return rgb, alpha, depth

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, g_rgb: Tensor, g_alpha: Tensor, g_depth: Tensor) -> tuple[Tensor | None, ...]:
        means2d, conics, opacities, colors, depths, background, alpha, t_final, last, kept_rows = ctx.saved_tensors
        bins: TileBins = ctx.bins
        grads = _ops().rasterize_backward(
            means2d,
            conics,
            opacities,
            colors,
            depths,
            background,
            *bins.raster_args(),
            bins.slots,
            bins.gauss_offsets,
            kept_rows,
            alpha,
            t_final,
            last,
            g_rgb,
            g_alpha,
            g_depth,
            *bins.grid_args(),
            torch.get_num_threads(),
        )
        return *grads, None


def bin_tiles(box: Tensor, depths: Tensor, visible: Tensor, width: int, height: int, tile_size: int) -> TileBins:
    """Per-tile, front-to-back lists of the visible Gaussians whose ``box`` (N, 4) meets each tile
    (depth ``depths`` (N,) ascending, ties in index order, as ``tiling.build_tile_lists``)."""
    order, ids, slots, tile_offsets, gauss_offsets = _ops().bin_tiles(
        box, depths.detach(), visible, width, height, tile_size, torch.get_num_threads()
    )
    return TileBins(
        order=order,
        ids=ids,
        tile_offsets=tile_offsets,
        slots=slots,
        gauss_offsets=gauss_offsets,
        box=box,
        tile_size=tile_size,
        width=width,
        height=height,
    )


@dataclass(frozen=True)
class _Prepared:
    """Projected, binned Gaussians and the compositing inputs cast to the rendering dtype."""

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    opacities: Tensor
    colors: Tensor
    background: Tensor
    bins: TileBins


def _project_and_bin(
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
    near: float,
    far: float,
    tile_size: int,
) -> _Prepared:
    """Project (differentiably) and bin the Gaussians; arguments as ``render_cpu``."""
    dtype = means.dtype
    if dtype not in DTYPES or means.device.type != "cpu":
        raise TypeError(f"the cpu backend takes float32/float64 CPU tensors, got {dtype} on {means.device}")
    quats, scales, opacities, colors, background = (
        t.to(dtype).contiguous() for t in (quats, scales, opacities, colors, background)
    )
    camera = _Camera(
        K.detach().to(torch.float64).contiguous(),
        world_to_cam.detach().to(torch.float64).contiguous(),
        width,
        height,
        float(near),
        float(far),
    )
    means2d, conics, depths, radii, box, visible = _Project.apply(means.contiguous(), quats, scales, opacities, camera)
    return _Prepared(
        means2d=means2d,
        conics=conics,
        depths=depths,
        radii=radii,
        opacities=opacities,
        colors=colors,
        background=background,
        bins=bin_tiles(box, depths, visible, width, height, tile_size),
    )


def render_cpu(
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
) -> RenderOutput:
    """Render N Gaussians with the compiled CPU rasterizer (arguments as ``render_gaussians``;
    float32 or float64 CPU tensors, computed in ``means.dtype``).

    ``tile_size`` (8 or 16, the compiled sizes) changes speed only, never the image.
    """
    prep = _project_and_bin(
        means, quats, scales, opacities, colors, K, world_to_cam, width, height, background, near, far, tile_size
    )
    if prep.means2d.requires_grad:
        prep.means2d.retain_grad()
    rgb, alpha, depth = _Rasterize.apply(
        prep.means2d, prep.conics, prep.opacities, prep.colors, prep.depths, prep.background, prep.bins
    )
    return RenderOutput(
        rgb=rgb, alpha=alpha, depth=depth, means2d=prep.means2d, radii=prep.radii, grad_holder=prep.means2d
    )


@torch.no_grad()
def work_counts(
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
) -> tuple[int, int]:
    """(alpha evaluations, contributing (Gaussian, pixel) pairs) of one forward pass (arguments as
    ``render_cpu``): the pixels of each Gaussian's box in each tile that had not stopped, and
    those the Gaussian was blended into. The benchmark's measure of the work done."""
    prep = _project_and_bin(
        means, quats, scales, opacities, colors, K, world_to_cam, width, height, background, near, far, tile_size
    )
    return tuple(
        _ops().rasterize_counts(
            prep.means2d,
            prep.conics,
            prep.opacities,
            prep.colors,
            prep.depths,
            prep.background,
            *prep.bins.raster_args(),
            *prep.bins.grid_args(),
            torch.get_num_threads(),
        )
    )
