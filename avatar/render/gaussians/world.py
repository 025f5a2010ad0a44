"""What the rasterizer draws: the Gaussians of one frame in world space, whatever model posed them."""

from __future__ import annotations

from typing import Protocol

from torch import Tensor


class WorldGaussians(Protocol):
    """Gaussians of one frame in world space: means (N, 3), scales (N, 3), quats (N, 4) (w, x, y, z), opacities
    (N,) in (0, 1), colors (N, 3) linear RGB."""

    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor
