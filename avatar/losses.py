"""Training losses of the paper (Eq. for L, L_s, L_mu), on tensors.

Regularisers act on the parameters in the parent triangle's local frame, in units of
the frame scale k (GaussianAvatars), and only on Gaussians visible in the current view.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from avatar.metrics.ssim import dssim_loss


def scale_regulariser(local_scales: Tensor, visible: Tensor, eps_s: float) -> Tensor:
    """L_s = || ReLU(s - eps_s) ||^2 averaged over visible Gaussians.

    Args:
        local_scales: (N, 3) linear scales in units of k (s + delta_s for the dynamic model).
        visible: (N,) bool.
        eps_s: threshold below which scales are free (paper: 0.4).
    """
    return visible_mean(torch.relu(local_scales - eps_s).square().sum(-1), visible)


def position_regulariser(local_means: Tensor, visible: Tensor, eps_mu: float) -> Tensor:
    """L_mu = || ReLU(|mu| - eps_mu) ||^2 averaged over visible Gaussians: keeps Gaussians within
    ``eps_mu`` (units of k, paper: 0.2) of their triangle's centre.

    Args:
        local_means: (N, 3) positions in the parent frame (mu + delta_mu for the dynamic model).
        visible: (N,) bool.
    """
    norms = torch.sqrt(local_means.square().sum(-1) + 1e-12)
    return visible_mean(torch.relu(norms - eps_mu).square(), visible)


def visible_mean(values: Tensor, visible: Tensor) -> Tensor:
    """The mean of per-Gaussian ``values`` (N,) over the ``visible`` (N,) ones; 0 (with a graph) where none is.

    On the CPU the visible values are gathered and averaged; on a GPU the others are masked to zero and the sum is
    divided by the count, which gives the same mean up to the order of the sum without the device telling the host
    how many Gaussians are visible (a wait every step)."""
    if values.is_cpu:
        kept = values[visible]
        return kept.mean() if kept.numel() else values.sum() * 0.0
    return masked_visible_mean(values, visible)


def masked_visible_mean(values: Tensor, visible: Tensor) -> Tensor:
    """:func:`visible_mean` as a GPU computes it: the invisible values masked to zero, the sum divided by the visible
    count (at least 1), every shape known before the values are."""
    return torch.where(visible, values, torch.zeros_like(values)).sum() / visible.sum().clamp_min(1)


def reconstruction_terms(
    pred: Tensor, gt: Tensor, local_scales: Tensor, local_means: Tensor, visible: Tensor, eps_s: float, eps_mu: float
) -> dict[str, Tensor]:
    """The terms both training stages share: ``l1``, ``dssim`` of a render ``pred`` against ``gt`` (S, S, 3),
    and ``scale_reg`` / ``position_reg`` (L_s, L_mu) of the visible Gaussians' local scales and means (N, 3)."""
    return {
        "l1": (pred - gt).abs().mean(),
        "dssim": dssim_loss(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]),
        "scale_reg": scale_regulariser(local_scales, visible, eps_s),
        "position_reg": position_regulariser(local_means, visible, eps_mu),
    }


def reconstruction_loss(
    terms: dict[str, Tensor], lambda_dssim: float, scale_weight: float, position_weight: float
) -> Tensor:
    """``(1 - lambda) L1 + lambda D-SSIM + a L_s + b L_mu`` (paper) from :func:`reconstruction_terms`."""
    return (
        (1 - lambda_dssim) * terms["l1"]
        + lambda_dssim * terms["dssim"]
        + scale_weight * terms["scale_reg"]
        + position_weight * terms["position_reg"]
    )


def patch_perceptual_loss(
    pred: Tensor, gt: Tensor, boxes: list[np.ndarray], lpips: nn.Module, min_size: int = 32
) -> Tensor:
    """L_patch: the sum over ``boxes`` of the LPIPS distance between the patches of ``pred`` and ``gt``.

    Args:
        pred, gt: (S, S, 3) images in [0, 1].
        boxes: (x0, y0, x1, y1) pixel boxes, exclusive end (the hand's box, the overlap of the hand and
            face boxes); each is grown about its centre to at least ``min_size`` pixels a side (within
            the image) so the backbone sees enough context.
        lpips: an :class:`avatar.metrics.LPIPS` (VGG in training, as the paper's perceptual loss).
    Returns:
        () loss; 0 (with a graph) when there is no box.
    """
    total = pred.sum() * 0.0
    size_y, size_x = pred.shape[:2]
    for box in boxes:
        x0, x1 = _grow(int(box[0]), int(box[2]), min_size, size_x)
        y0, y1 = _grow(int(box[1]), int(box[3]), min_size, size_y)
        a = pred[y0:y1, x0:x1].permute(2, 0, 1)
        b = gt[y0:y1, x0:x1].permute(2, 0, 1)
        total = total + lpips(a, b, unit_range=True)
    return total


def _grow(lo: int, hi: int, min_size: int, limit: int) -> tuple[int, int]:
    """[lo, hi) grown about its centre to at least ``min(min_size, limit)``, kept inside [0, limit)."""
    size = min(max(hi - lo, min_size), limit)
    start = min(max((lo + hi - size) // 2, 0), limit - size)
    return start, start + size
