"""The evaluation summary: consistency with the individual metrics, regions, empty masks."""

from __future__ import annotations

import math

import pytest
import torch

from avatar.metrics import LPIPS, image_metrics, psnr, ssim
from avatar.metrics.lpips_weights import INSTALL_COMMAND, LPIPSWeightsNotFoundError, weight_file

try:
    weight_file("alex")
except LPIPSWeightsNotFoundError:
    pytest.skip(f"LPIPS weights not installed: {INSTALL_COMMAND}", allow_module_level=True)


@pytest.fixture(scope="module")
def lpips() -> LPIPS:
    return LPIPS("alex")


@pytest.fixture
def pair() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(2, 3, 40, 36, generator=g)
    return (gt + 0.05 * torch.randn(gt.shape, generator=g)).clamp(0, 1), gt


def test_full_image(pair, lpips):
    pred, gt = pair
    out = image_metrics(pred[0], gt[0], lpips_model=lpips)
    assert set(out) == {"psnr", "ssim", "lpips"} and all(isinstance(v, float) for v in out.values())
    assert out["psnr"] == pytest.approx(psnr(pred[0], gt[0]).item(), abs=1e-4)
    assert out["ssim"] == pytest.approx(ssim(pred[0], gt[0]).item(), abs=1e-6)
    assert out["lpips"] == pytest.approx(lpips(pred[0], gt[0], unit_range=True).item(), abs=1e-6)
    batch = image_metrics(pred, gt, lpips_model=lpips)  # mean over the images
    assert batch["psnr"] == pytest.approx(psnr(pred, gt).mean().item(), abs=1e-4)
    perfect = image_metrics(gt, gt)  # the shared default model
    assert math.isinf(perfect["psnr"]) and perfect["ssim"] == pytest.approx(1.0) and perfect["lpips"] == 0.0


def test_regions_and_empty_masks(pair, lpips):
    pred, gt = pair
    mask = torch.zeros(2, 40, 36, dtype=torch.bool)
    mask[0, 5:30, 8:30] = True  # image 1: empty mask
    out = image_metrics(pred, gt, mask, lpips_model=lpips)
    region = image_metrics(pred[0], gt[0], mask[0], lpips_model=lpips)
    assert out == pytest.approx(region)  # the image with the empty mask is skipped
    assert region["psnr"] == pytest.approx(psnr(pred[0], gt[0], mask[0]).item(), abs=1e-4)
    assert region["lpips"] == pytest.approx(lpips(pred[0] * mask[0], gt[0] * mask[0], unit_range=True).item(), abs=1e-6)
    empty = image_metrics(pred[1], gt[1], mask[1], lpips_model=lpips)
    assert all(math.isnan(v) for v in empty.values())
