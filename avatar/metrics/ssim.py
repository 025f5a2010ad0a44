"""SSIM (Wang et al. 2004) with a Gaussian window, as in 3DGS and scikit-image, and the D-SSIM loss.

Definition
----------
Per channel, local statistics are Gaussian-weighted (11 x 11 window, sigma 1.5,
weights normalised to sum 1; separable), population (co)variances, and

    SSIM = (2 mu_x mu_y + C1) (2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1) (s_x^2 + s_y^2 + C2))

with ``C1 = 0.01^2`` and ``C2 = 0.03^2`` (data range 1: images in [0, 1]).
The denominator is at least ``C1 * C2``, so values and gradients are finite
for any finite input, constant images included (identical images give 1).

Borders (``padding``)
---------------------
* ``"valid"`` (the metric's default): the map has one value per *complete*
  window, shape ``(H - 10, W - 10)``, the value at map pixel (i, j) belonging
  to the window centred on image pixel (i + 5, j + 5). Its mean equals
  ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)``
  exactly, because skimage crops its (reflect-padded) map by
  ``(win_size - 1) // 2 = 5`` before averaging, keeping exactly the complete
  windows. Images with a side below 11 have no complete window: the map is
  empty and the SSIM is NaN (undefined), where skimage raises.
* ``"zero"`` (3DGS ``ssim``, used by :func:`dssim_loss`): zero padding, the
  map has the image's shape, any image size >= 1 works.

Masked SSIM is the (weighted) mean of the map over the mask's pixels and all
channels; in ``"valid"`` mode the mask is cropped like the map (a map value
counts if its window centre is in the mask). An empty mask gives NaN.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from avatar.metrics._images import as_batch, mask_weights, masked_mean, unbatch

WINDOW_SIZE = 11
SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2
_RADIUS = WINDOW_SIZE // 2

Padding = Literal["valid", "zero"]


def gaussian_window(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """The normalised 1D Gaussian ``(11,)`` (sigma 1.5); its outer product is the 2D SSIM window."""
    x = torch.arange(WINDOW_SIZE, dtype=dtype, device=device) - _RADIUS
    g = torch.exp(-(x**2) / (2 * SIGMA**2))
    return g / g.sum()


def _correlate_axis(x: Tensor, weights: list[float], dim: int, pad: int) -> Tensor:
    """Correlate ``x`` along ``dim`` (-1 or -2) with the taps ``weights`` (K,) after zero-padding ``pad`` on
    both sides; the axis shrinks to ``n + 2 pad - K + 1``. A sum of K shifted slices: on CPU, for these
    one-channel planes, D-SSIM with it ran 14x (128 px) to 31x (256 px) faster than with ``conv2d``'s oneDNN
    path on a Zen 4 core, and 4-6x faster than with its native path (benchmarks/bench_ssim.py)."""
    if pad:
        x = F.pad(x, (pad, pad) if dim == -1 else (0, 0, pad, pad))
    n_out = x.shape[dim] - len(weights) + 1
    out = x.narrow(dim, 0, n_out) * weights[0]
    for k, w in enumerate(weights[1:], start=1):
        out.add_(x.narrow(dim, k, n_out), alpha=w)
    return out


class _SeparableBlur(torch.autograd.Function):
    """The separable Gaussian filter of :func:`_blur` with its adjoint as backward (one graph node instead of
    22 slice operations). Correlation with zero padding ``p`` has as adjoint the correlation with the flipped
    taps (the same: the window is symmetric) and padding ``K - 1 - p``."""

    @staticmethod
    def forward(ctx, planes: Tensor, weights: list[float], pad: int) -> Tensor:
        ctx.weights, ctx.adjoint_pad = weights, len(weights) - 1 - pad
        return _correlate_axis(_correlate_axis(planes, weights, -1, pad), weights, -2, pad)

    @staticmethod
    @once_differentiable  # a second derivative would need the adjoint's graph: raise instead of a silent zero
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        w, p = ctx.weights, ctx.adjoint_pad
        return _correlate_axis(_correlate_axis(grad, w, -2, p), w, -1, p), None, None


def _blur(x: Tensor, padding: Padding) -> Tensor:
    """Gaussian-filter every channel of ``x`` ``(N, K, H, W)`` separably; ``(N, K, H', W')`` per ``padding``."""
    weights = gaussian_window(torch.float64, "cpu").tolist()  # the taps, numbers on the host
    return _SeparableBlur.apply(x, weights, _RADIUS if padding == "zero" else 0)


def _ssim_map(x: Tensor, y: Tensor, padding: Padding) -> Tensor:
    """SSIM map of batches ``(B, C, H, W)``: ``(B, C, H', W')`` (see the module docstring for H', W')."""
    if padding not in ("valid", "zero"):
        raise ValueError(f"padding must be 'valid' or 'zero', got {padding!r}")
    b, c, h, w = x.shape
    if padding == "valid" and (h < WINDOW_SIZE or w < WINDOW_SIZE):
        return x.new_empty(b, c, max(h - 2 * _RADIUS, 0), max(w - 2 * _RADIUS, 0))
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), padding)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(c, dim=1)
    mu_xy = mu_x * mu_y
    mu_xx = mu_x * mu_x
    mu_yy = mu_y * mu_y
    num = (2 * mu_xy + C1) * (2 * (e_xy - mu_xy) + C2)
    den = (mu_xx + mu_yy + C1) * ((e_xx - mu_xx) + (e_yy - mu_yy) + C2)
    return num / den


def _map_weights(mask: Tensor | None, like: Tensor, padding: Padding) -> Tensor | None:
    """Mask weights ``(B, 1, H', W')`` aligned with the SSIM map of images ``like`` ``(B, C, H, W)``."""
    if mask is None:
        return None
    weights = mask_weights(mask, like)
    return weights[..., _RADIUS:-_RADIUS, _RADIUS:-_RADIUS] if padding == "valid" else weights


def ssim_map(pred: Tensor, gt: Tensor, padding: Padding = "valid") -> Tensor:
    """Per-pixel, per-channel SSIM map.

    Args:
        pred, gt: ``(C, H, W)`` or ``(B, C, H, W)`` images in [0, 1].
        padding: ``"valid"`` (complete windows only, skimage) or ``"zero"`` (3DGS).

    Returns:
        ``([B,] C, H - 10, W - 10)`` for ``"valid"`` (empty if a side is below 11),
        ``([B,] C, H, W)`` for ``"zero"``; values in [-1, 1].
    """
    x, y, batched = as_batch(pred, gt)
    smap = _ssim_map(x, y, padding)
    return unbatch(smap, batched)


def ssim(pred: Tensor, gt: Tensor, mask: Tensor | None = None, padding: Padding = "valid") -> Tensor:
    """Mean SSIM per image, optionally over a mask. Differentiable.

    Args:
        pred, gt: ``(C, H, W)`` or ``(B, C, H, W)`` images in [0, 1].
        mask: optional region (see :mod:`avatar.metrics._images`), ``(H, W)`` ... ``(B, 1, H, W)``.
        padding: ``"valid"`` (default; equals skimage's value) or ``"zero"`` (3DGS).

    Returns:
        ``()`` or ``(B,)``: SSIM in [-1, 1]; NaN for an empty mask or, with
        ``"valid"``, an image with a side below 11 (no complete window).
    """
    x, y, batched = as_batch(pred, gt)
    smap = _ssim_map(x, y, padding)
    return unbatch(masked_mean(smap, _map_weights(mask, x, padding)), batched)


def dssim_loss(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """The D-SSIM training loss ``1 - SSIM`` (3DGS: zero padding, any image size).

    The SSIM map is averaged over all pixels and channels of the batch (or over
    the masked pixels of the whole batch, weighted by the mask), so each pixel
    counts equally.

    Args:
        pred: ``(C, H, W)`` or ``(B, C, H, W)`` rendered images in [0, 1].
        gt: same shape, target images in [0, 1].
        mask: optional region weights (see :mod:`avatar.metrics._images`).

    Returns:
        A scalar in [0, 2]; 0 (with zero gradient) when the mask is empty over
        the whole batch, so a batch without the region adds no loss and no NaN.
    """
    x, y, _ = as_batch(pred, gt)
    smap = _ssim_map(x, y, "zero")
    weights = _map_weights(mask, x, "zero")
    # Pool the batch into one image: (1, C, B*H*W, 1), weights (1, 1, B*H*W, 1).
    pooled = smap.transpose(0, 1).flatten(1)[None, ..., None]
    pooled_weights = None if weights is None else weights.transpose(0, 1).flatten(1)[None, ..., None]
    return 1 - masked_mean(pooled, pooled_weights, empty=1.0)[0]
