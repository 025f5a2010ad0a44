"""Input handling shared by the image metrics: batching, masks and masked means.

Conventions (all metrics)
-------------------------
* Images are torch tensors, channels first: one image ``(C, H, W)`` or a batch
  ``(B, C, H, W)``; ``pred`` and ``gt`` have the same shape, a floating dtype,
  and values in [0, 1] unless a function says otherwise.
* A mask selects the pixels a region metric is computed on. It has shape
  ``(H, W)``, ``(B, H, W)``, ``(1, H, W)`` or ``(B, 1, H, W)`` (whatever
  broadcasts to ``(B, 1, H, W)``), and is boolean or a float weight in [0, 1]
  (a soft mask weights pixels; a binary mask selects them). It applies to all
  channels.
* An empty mask (total weight 0) leaves the region metric undefined: the value
  is NaN, never an exception.
"""

from __future__ import annotations

import torch
from torch import Tensor


def as_batch(pred: Tensor, gt: Tensor) -> tuple[Tensor, Tensor, bool]:
    """Check a (pred, gt) pair and view it as a batch.

    Args:
        pred, gt: ``(C, H, W)`` or ``(B, C, H, W)`` floating tensors of equal shape.

    Returns:
        ``(pred, gt, batched)`` with both images ``(B, C, H, W)`` and ``batched``
        telling whether the input had a batch dimension (use :func:`unbatch` on results).
    """
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if pred.ndim not in (3, 4):
        raise ValueError(f"images must be (C, H, W) or (B, C, H, W), got shape {tuple(pred.shape)}")
    if not (pred.is_floating_point() and gt.is_floating_point()):
        raise TypeError(f"images must be floating point tensors, got {pred.dtype} and {gt.dtype}")
    batched = pred.ndim == 4
    return (pred, gt, True) if batched else (pred[None], gt[None], False)


def unbatch(values: Tensor, batched: bool) -> Tensor:
    """Per-image results ``(B, ...)`` as returned to the caller: unchanged if the input was batched, else ``[0]``."""
    return values if batched else values[0]


def mask_weights(mask: Tensor, like: Tensor) -> Tensor:
    """A mask as per-pixel weights ``(B, 1, H, W)`` in the dtype and device of ``like`` ``(B, C, H, W)``."""
    if mask.ndim == 2:
        mask = mask[None, None]
    elif mask.ndim == 3:
        mask = mask[:, None]
    elif mask.ndim != 4:
        raise ValueError(f"mask must be (H, W), (B, H, W) or (B, 1, H, W), got shape {tuple(mask.shape)}")
    b, _, h, w = like.shape
    try:
        weights = torch.broadcast_to(mask, (b, 1, h, w))
    except RuntimeError as err:
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not fit images of shape {tuple(like.shape)}") from err
    weights = weights.to(device=like.device, dtype=like.dtype)
    if not bool(((weights >= 0) & (weights <= 1)).all()):
        raise ValueError("mask weights must lie in [0, 1] (and not be NaN)")
    return weights


def masked_mean(values: Tensor, weights: Tensor | None, empty: float = float("nan")) -> Tensor:
    """Weighted mean of ``values`` over pixels and channels, per image.

    Args:
        values: ``(B, C, H, W)``.
        weights: ``(B, 1, H, W)`` in [0, 1] from :func:`mask_weights`, or None for the plain mean.
        empty: the result for an image whose weights sum to 0 (default NaN: undefined).

    Returns:
        ``(B,)``: ``sum(w * v) / (C * sum(w))``. Gradients stay finite (zero) for empty masks.
    """
    if weights is None:
        return values.mean(dim=(1, 2, 3))
    total = weights.sum(dim=(1, 2, 3)) * values.shape[1]
    defined = total > 0
    mean = (values * weights).sum(dim=(1, 2, 3)) / torch.where(defined, total, torch.ones_like(total))
    return torch.where(defined, mean, torch.full_like(mean, empty))
