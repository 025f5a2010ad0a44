"""PSNR, SSIM and LPIPS of a rendered image against its ground truth, for the evaluation stage."""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from avatar.metrics._images import as_batch, mask_weights
from avatar.metrics.lpips import LPIPS
from avatar.metrics.psnr import psnr
from avatar.metrics.ssim import ssim


@functools.cache
def default_lpips() -> LPIPS:
    """The shared LPIPS-alex metric module (weights read on first use)."""
    return LPIPS("alex")


def _batch_mean(values: Tensor) -> float:
    """Mean of the defined (non-NaN) per-image values ``(B,)``; NaN if none is defined."""
    defined = values[~values.isnan()]
    return float(defined.mean()) if defined.numel() else math.nan


@torch.no_grad()
def image_metrics(
    pred: Tensor, gt: Tensor, mask: Tensor | None = None, lpips_model: LPIPS | None = None
) -> dict[str, float]:
    """PSNR (dB), SSIM and LPIPS-alex of rendered images, optionally restricted to a region.

    Region (``mask``) definitions: PSNR is over the masked pixels (see
    :mod:`avatar.metrics.psnr`); SSIM is the mean of the SSIM map over the
    mask (skimage-equivalent ``"valid"`` borders, see :mod:`avatar.metrics.ssim`);
    LPIPS compares both images composited onto black by the mask
    (``pred * m`` vs ``gt * m``), i.e. only the region's content is seen.

    Args:
        pred: ``(3, H, W)`` or ``(B, 3, H, W)`` rendered images in [0, 1]; H, W >= 31.
        gt: same shape, ground-truth images in [0, 1].
        mask: optional region, ``(H, W)`` ... ``(B, 1, H, W)``, bool or weights in [0, 1].
        lpips_model: the LPIPS module to use (default: the shared alex one).

    Returns:
        ``{"psnr", "ssim", "lpips"}``: each the mean over the images of the batch
        for which it is defined. An image with an empty mask contributes NaN
        per metric and is skipped; a value is NaN only if no image defines it.
        PSNR is ``inf`` if the images are identical.
    """
    x, y, _ = as_batch(pred, gt)
    weights = None if mask is None else mask_weights(mask, x)
    model = lpips_model if lpips_model is not None else default_lpips()
    model.to(x.device)
    if weights is None:
        lpips_values = model(x.float(), y.float(), unit_range=True)
    else:
        lpips_values = model((x * weights).float(), (y * weights).float(), unit_range=True)
        lpips_values = lpips_values.masked_fill(weights.sum(dim=(1, 2, 3)) == 0, math.nan)
    return {
        "psnr": _batch_mean(psnr(x, y, weights)),
        "ssim": _batch_mean(ssim(x, y, weights)),
        "lpips": _batch_mean(lpips_values),
    }
