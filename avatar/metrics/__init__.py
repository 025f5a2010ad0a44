"""Image metrics and losses: PSNR, SSIM / D-SSIM, LPIPS (alex, vgg), and their evaluation summary.

All take torch images channels-first, ``(C, H, W)`` or ``(B, C, H, W)``, in
[0, 1] (LPIPS: [-1, 1] unless ``unit_range=True``), and an optional region
mask; an empty mask gives NaN, not an exception. See ``_images`` for the
conventions, and each module for its exact definition.
"""

from avatar.metrics.evaluation import image_metrics
from avatar.metrics.lpips import LPIPS
from avatar.metrics.lpips_weights import INSTALL_COMMAND, LPIPSWeightsNotFoundError
from avatar.metrics.psnr import mse, psnr
from avatar.metrics.ssim import dssim_loss, ssim, ssim_map

__all__ = [
    "INSTALL_COMMAND",
    "LPIPS",
    "LPIPSWeightsNotFoundError",
    "dssim_loss",
    "image_metrics",
    "mse",
    "psnr",
    "ssim",
    "ssim_map",
]
