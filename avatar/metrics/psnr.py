"""PSNR of [0, 1] images, over the whole image or over a mask (region metrics).

``PSNR = 10 log10(1 / MSE)`` (data range 1) where, for a mask with weights
``m`` (binary: the region's pixels), ``MSE = sum(m * (pred - gt)^2) / (C * sum(m))``:
the mean squared error over the masked pixels and all C channels. Without a
mask, every pixel counts. Region metrics (``full``, ``hand``, ``face``,
``interaction``) are this function with the region's mask.

Special values, never exceptions: identical images (MSE 0) give ``+inf``;
an empty mask gives NaN (no pixel, so the region's error is undefined; the
caller decides whether to skip the frame).
"""

from __future__ import annotations

import torch
from torch import Tensor

from avatar.metrics._images import as_batch, mask_weights, masked_mean, unbatch


def mse(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean squared error per image over (masked) pixels and channels.

    Args:
        pred, gt: ``(C, H, W)`` or ``(B, C, H, W)`` images in [0, 1].
        mask: optional region, ``(H, W)`` ... ``(B, 1, H, W)``, bool or weights in [0, 1].

    Returns:
        ``()`` or ``(B,)``, >= 0; NaN for an empty mask.
    """
    x, y, batched = as_batch(pred, gt)
    weights = None if mask is None else mask_weights(mask, x)
    return unbatch(masked_mean((x - y).square(), weights), batched)


def psnr(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """PSNR in dB per image (data range 1), optionally over a mask.

    Args:
        pred, gt: ``(C, H, W)`` or ``(B, C, H, W)`` images in [0, 1].
        mask: optional region, ``(H, W)`` ... ``(B, 1, H, W)``, bool or weights in [0, 1].

    Returns:
        ``()`` or ``(B,)``: ``-10 log10(MSE)``; ``+inf`` for identical images, NaN for an empty mask.
    """
    return -10 * torch.log10(mse(pred, gt, mask))
