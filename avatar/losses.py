"""Training losses of the paper (Eq. for L, L_s, L_mu), on tensors.

Regularisers act on the parameters in the parent triangle's local frame, in units of
the frame scale k (GaussianAvatars), and only on Gaussians visible in the current view.
"""

from __future__ import annotations

import torch
from torch import Tensor


def scale_regulariser(local_scales: Tensor, visible: Tensor, eps_s: float) -> Tensor:
    """L_s = || ReLU(s - eps_s) ||^2 averaged over visible Gaussians.

    Args:
        local_scales: (N, 3) linear scales in units of k (s + delta_s for the dynamic model).
        visible: (N,) bool.
        eps_s: threshold below which scales are free (paper: 0.4).
    """
    excess = torch.relu(local_scales[visible] - eps_s)
    return excess.square().sum(-1).mean() if excess.numel() else local_scales.sum() * 0.0


def position_regulariser(local_means: Tensor, visible: Tensor, eps_mu: float) -> Tensor:
    """L_mu = || ReLU(|mu| - eps_mu) ||^2 averaged over visible Gaussians: keeps Gaussians within
    ``eps_mu`` (units of k, paper: 0.2) of their triangle's centre.

    Args:
        local_means: (N, 3) positions in the parent frame (mu + delta_mu for the dynamic model).
        visible: (N,) bool.
    """
    norms = torch.sqrt(local_means[visible].square().sum(-1) + 1e-12)
    excess = torch.relu(norms - eps_mu)
    return excess.square().mean() if excess.numel() else local_means.sum() * 0.0
