"""Front-to-back alpha compositing of per-tile Gaussian lists, with a hand-written backward.

Per pixel ``p`` and its tile's depth-sorted list ``k = 0, 1, ...`` (3DGS maths):

    alpha_k = min(ALPHA_MAX, o_k exp(-d^T conic_k d / 2)), set to 0 where below ALPHA_MIN
    rho_k   = prod_{j <= k} (1 - alpha_j)                     (transmittance after k)
    w_k     = alpha_k rho_{k-1}   if rho_k >= T_MIN else 0    (the early stop, as a mask)
    feat    = sum_k w_k f_k,   acc = sum_k w_k

so ``1 - acc`` is the final transmittance. The reference kernel stops at the first Gaussian
that would take the transmittance below ``T_MIN``; since ``rho`` only decreases, the mask
selects exactly the same prefix.

Dense layout. The exponent is a quadratic in the pixel coordinates, so with coordinates
relative to the tile centre it is ``coef (6,) . [1, x, y, x^2, xy, y^2]``: one matrix product
against a (6, tile_size^2) pixel basis evaluates a whole (list entries x tiles x pixels)
block. The work runs in *steps*: ``round_len`` consecutive list entries of up to
``max_chunk_elements / (round_len * tile_size^2)`` tiles, in depth order, carrying each
pixel's transmittance from step to step. A tile leaves the schedule when its list ends or
all its pixels have stopped, so memory is bounded by ``max_chunk_elements`` and occluded
Gaussians cost nothing.

Backward. Each step is recomputed (nothing dense is stored) in reverse order, carrying per
pixel ``R = sum of w_j v_j over later steps``, where ``v_j = f_j . dL/dfeat + dL/dacc``:

    dL/dalpha_k = rho_{k-1} v_k - (sum_{j > k} w_j v_j) / (1 - alpha_k)

zero where ``alpha_k`` is clamped, skipped or masked by the early stop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .projection import ALPHA_MIN
from .tiling import TileLists, image_to_tiles, tiles_to_image

#: Upper clamp of a Gaussian's alpha at a pixel.
ALPHA_MAX = 0.99
#: A pixel stops compositing before the Gaussian that would take its transmittance below this.
T_MIN = 1e-4
#: Leading columns of the Gaussian table: mean x, mean y, conic a, b, c, log opacity.
GEOMETRY_COLUMNS = 6
_PAD_LOG_OPACITY = -1e4  # padding entries: exp(-1e4) == 0


@dataclass(frozen=True)
class CompositeSettings:
    """Work sizes of the dense steps (they change speed and memory, never the image).

    Attributes:
        round_len: list entries per tile per step.
        max_chunk_elements: upper bound on ``entries x tiles x tile pixels`` of one step.
    """

    round_len: int = 32
    max_chunk_elements: int = 1 << 21


def pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Monomials (6, tile_size^2) ``[1, x, y, x^2, xy, y^2]`` of the tile's pixel centres, row-major,
    in coordinates relative to the tile centre."""
    r = torch.arange(tile_size, dtype=dtype, device=device) - (tile_size - 1) / 2.0
    y, x = torch.meshgrid(r, r, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y])


def exponent_coefficients(geom: Tensor, centres: Tensor) -> Tensor:
    """Coefficients (6, M) of ``log o - q(x - u, y - v) / 2`` on the monomials of ``pixel_basis``.

    Args:
        geom: (6, M) columns ``mean x, mean y, conic a, b, c, log o`` of M (entry, tile) pairs.
        centres: (2, M) pixel coordinates of the pairs' tile centres; ``(u, v) = mean - centre``.
    """
    u, v = geom[0] - centres[0], geom[1] - centres[1]
    a, b, c, log_o = geom[2], geom[3], geom[4], geom[5]
    gu, gv = a * u + b * v, b * u + c * v
    return torch.stack([log_o - 0.5 * (u * gu + v * gv), gu, gv, -0.5 * a, -b, -0.5 * c])


def exponent_coefficients_vjp(geom: Tensor, centres: Tensor, d_coef: Tensor) -> Tensor:
    """Vector-Jacobian product of ``exponent_coefficients``: d_coef (6, M) -> (6, M) on ``geom``."""
    u, v = geom[0] - centres[0], geom[1] - centres[1]
    a, b, c = geom[2], geom[3], geom[4]
    d0, d1, d2, d3, d4, d5 = d_coef
    return torch.stack(
        [
            d1 * a + d2 * b - d0 * (a * u + b * v),
            d1 * b + d2 * c - d0 * (b * u + c * v),
            u * (d1 - 0.5 * d0 * u) - 0.5 * d3,
            v * d1 + u * (d2 - d0 * v) - d4,
            v * (d2 - 0.5 * d0 * v) - 0.5 * d5,
            d0,
        ]
    )


def _indicator(compare: Callable[..., Tensor], x: Tensor, threshold: float) -> Tensor:
    """Float 0/1 tensor of ``compare(x, threshold)`` for a comparison such as ``torch.ge``.

    Comparing straight into a float output is several times faster on the CPU than a bool
    mask followed by a cast or ``torch.where``.
    """
    return compare(x, threshold, out=torch.empty_like(x))


@dataclass
class _Step:
    """One dense step of the schedule: list entries ``[start, start + length)`` of ``tiles``."""

    tiles: Tensor  # (A,) int64
    start: int
    length: int
    t_in: Tensor  # (A, P) transmittance before the step


@dataclass
class _Dense:
    """Recomputable per-(entry, tile, pixel) quantities of one step, each (L, A, P)."""

    alpha: Tensor
    one_minus: Tensor  # 1 - alpha
    t_prev: Tensor  # transmittance before the entry
    alpha_kept: Tensor  # alpha, 0 where the early stop masks the entry
    weight: Tensor  # w = alpha_kept * t_prev


class _Compositor:
    """The schedule of dense steps over a tile grid and the maths of one step.

    The Gaussian table is held as columns (D, N + 1) (the last one is the padding entry), so
    that gathering and scattering entries move contiguous (entries,) vectors per column.
    """

    def __init__(self, table: Tensor, lists: TileLists, settings: CompositeSettings) -> None:
        self.lists = lists
        self.settings = settings
        self.basis = pixel_basis(lists.tile_size, table.dtype, table.device)
        pad = table.new_zeros(1, table.shape[1])
        pad[0, GEOMETRY_COLUMNS - 1] = _PAD_LOG_OPACITY
        self.columns = torch.cat([table, pad]).T.contiguous()
        self.pad_row = table.shape[0]
        limit = torch.tensor(ALPHA_MIN, dtype=table.dtype, device="cpu")  # a number for the host
        self.below_alpha_min = float(torch.nextafter(limit, torch.zeros_like(limit)))

    def gather(self, step: _Step) -> tuple[Tensor, Tensor, Tensor]:
        """Table columns (D, M) of a step's M = L * A entries (entry-major), their table rows (M,)
        (padding -> the pad row) and their tile centres (2, M)."""
        pos = step.start + torch.arange(step.length, device=step.tiles.device)[:, None]
        valid = pos < self.lists.counts[step.tiles]
        flat = (self.lists.offsets[step.tiles] + pos).clamp_max(self.lists.ids.numel() - 1).reshape(-1)
        # int64 indices: index_add_ with int32 ones takes a path several times slower.
        ids = self.lists.ids.index_select(0, flat).long()
        row_ids = torch.where(valid.reshape(-1), ids, self.pad_row)
        centres = self.lists.tile_centres(step.tiles, self.columns.dtype).T.repeat(1, step.length)
        return self.columns.index_select(1, row_ids), row_ids, centres

    def dense(self, cols: Tensor, centres: Tensor, t_in: Tensor) -> _Dense:
        """Alphas, transmittances and weights (L, A, P) of one step from its gathered columns
        (D, L * A), tile centres (2, L * A) and incoming transmittance (A, P)."""
        tiles, num_pixels = t_in.shape
        coef = exponent_coefficients(cols[:GEOMETRY_COLUMNS], centres)
        exponent = (coef.T @ self.basis).view(-1, tiles, num_pixels)
        # threshold() keeps x > value: the float just below ALPHA_MIN makes it x >= ALPHA_MIN.
        alpha = torch.threshold(exponent.exp_(), self.below_alpha_min, 0.0).clamp_max_(ALPHA_MAX)
        one_minus = torch.rsub(alpha, 1.0)
        t_prev = torch.empty_like(alpha)
        t_prev[0] = t_in
        for k in range(1, alpha.shape[0]):
            torch.mul(t_prev[k - 1], one_minus[k - 1], out=t_prev[k])
        alpha_kept = _indicator(torch.ge, t_prev * one_minus, T_MIN).mul_(alpha)
        return _Dense(
            alpha=alpha, one_minus=one_minus, t_prev=t_prev, alpha_kept=alpha_kept, weight=alpha_kept * t_prev
        )

    @staticmethod
    def features(cols: Tensor, step: _Step) -> Tensor:
        """Features (L, A, C) of a step's gathered columns, contiguous (``bmm`` copies per batch
        item otherwise)."""
        return cols[GEOMETRY_COLUMNS:].view(-1, step.length, step.tiles.numel()).permute(1, 2, 0).contiguous()

    def schedule_forward(self, valid_pixels: Tensor) -> tuple[Tensor, Tensor, list[_Step]]:
        """Composite every tile; returns features (T, P, C), accumulated alpha (T, P) and the steps.

        ``valid_pixels`` (T, P) is 1 for pixels inside the image and 0 for the padding of border
        tiles (their transmittance starts at 0, so they never hold a tile in the schedule).
        """
        lists, cfg = self.lists, self.settings
        num_pixels = self.basis.shape[1]
        feat = self.columns.new_zeros(lists.num_tiles, num_pixels, self.columns.shape[0] - GEOMETRY_COLUMNS)
        acc = self.columns.new_zeros(lists.num_tiles, num_pixels)
        trans = valid_pixels.clone()
        tiles_per_step = max(1, cfg.max_chunk_elements // (cfg.round_len * num_pixels))
        active = torch.argsort(lists.counts, descending=True, stable=True)
        active = active[lists.counts[active] > 0]
        steps: list[_Step] = []
        start = 0
        while active.numel() > 0:
            for tiles in active.split(tiles_per_step):
                length = min(cfg.round_len, int(lists.counts[tiles[0]]) - start)
                step = _Step(tiles=tiles, start=start, length=length, t_in=trans[tiles])
                cols, _, centres = self.gather(step)
                d = self.dense(cols, centres, step.t_in)
                feat.index_add_(0, tiles, torch.einsum("lap,lac->apc", d.weight, self.features(cols, step)))
                acc.index_add_(0, tiles, d.weight.sum(0))
                trans[tiles] = d.t_prev[-1] * d.one_minus[-1]
                steps.append(step)
            start += cfg.round_len
            active = active[(lists.counts[active] > start) & (trans[active].amax(1) >= T_MIN)]
        return feat, acc, steps

    def schedule_backward(self, steps: list[_Step], grad_feat: Tensor, grad_acc: Tensor) -> Tensor:
        """Gradient (N, D) of the table given gradients of the tile features (T, P, C) and alpha (T, P)."""
        grad_columns = torch.zeros_like(self.columns)
        later = torch.zeros_like(grad_acc)  # R: sum of w v over the steps after the current one
        for step in reversed(steps):
            cols, row_ids, centres = self.gather(step)
            d = self.dense(cols, centres, step.t_in)
            g_feat = grad_feat[step.tiles]
            v = torch.einsum("lac,apc->lap", self.features(cols, step), g_feat).add_(grad_acc[step.tiles])
            wv = d.weight * v
            after = torch.empty_like(wv)  # sum_{j > k} w_j v_j, including later steps
            after[-1] = later[step.tiles]
            for k in range(step.length - 2, -1, -1):
                torch.add(after[k + 1], wv[k + 1], out=after[k])
            later[step.tiles] = after[0] + wv[0]
            # dL/dexponent = alpha dL/dalpha = alpha_kept (t_prev v - after / (1 - alpha)) where alpha is
            # not clamped; alpha_kept vanishes wherever alpha is skipped or masked by the early stop.
            d_exponent = wv.sub_(after.div_(d.one_minus).mul_(d.alpha_kept))
            d_exponent.mul_(_indicator(torch.lt, d.alpha, ALPHA_MAX))
            d_coef = self.basis @ d_exponent.view(-1, d_exponent.shape[-1]).T  # (6, L * A)
            d_geom = exponent_coefficients_vjp(cols[:GEOMETRY_COLUMNS], centres, d_coef)
            d_feat = torch.einsum("lap,apc->lac", d.weight, g_feat).reshape(row_ids.numel(), -1).T
            grad_columns.index_add_(1, row_ids, torch.cat([d_geom, d_feat]))
        return grad_columns[:, : self.pad_row].T


class _TileComposite(torch.autograd.Function):
    """(N, 6 + C) Gaussian table -> (H, W, C) features and (H, W) accumulated alpha."""

    @staticmethod
    def forward(
        ctx: Any, table: Tensor, lists: TileLists, width: int, height: int, settings: CompositeSettings
    ) -> tuple[Tensor, Tensor]:
        comp = _Compositor(table, lists, settings)
        valid = image_to_tiles(table.new_ones(height, width, 1), lists)[..., 0]
        feat, acc, steps = comp.schedule_forward(valid)
        ctx.compositor, ctx.steps = comp, steps
        alpha = tiles_to_image(acc[..., None], lists, width, height)[..., 0]
        return tiles_to_image(feat, lists, width, height), alpha

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_feat: Tensor, grad_acc: Tensor) -> tuple[Tensor | None, ...]:
        comp: _Compositor = ctx.compositor
        grad_table = comp.schedule_backward(
            ctx.steps, image_to_tiles(grad_feat, comp.lists), image_to_tiles(grad_acc[..., None], comp.lists)[..., 0]
        )
        return grad_table, None, None, None, None


def composite(
    table: Tensor, lists: TileLists, width: int, height: int, settings: CompositeSettings = CompositeSettings()
) -> tuple[Tensor, Tensor]:
    """Composite the Gaussians of ``table`` over the tile lists.

    Args:
        table: (N, 6 + C) rows ``[mean x, mean y, conic a, b, c, log opacity, features (C)]``;
            only rows referenced by ``lists`` are read.
        lists: depth-sorted per-tile lists (``tiling.build_tile_lists``).
        width, height: image size in pixels.
        settings: dense step sizes.

    Returns:
        features (H, W, C) ``sum_k w_k f_k`` and accumulated alpha (H, W) ``sum_k w_k``.
    """
    return _TileComposite.apply(table, lists, width, height, settings)
