"""PSNR: agreement with scikit-image, masked (region) definition, special values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio

from avatar.metrics import mse, psnr


@pytest.fixture
def pair() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(2, 3, 17, 23, generator=g, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn(gt.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return pred, gt


def test_matches_skimage(pair):
    pred, gt = pair
    ours = psnr(pred, gt)
    assert ours.shape == (2,)
    for b in range(2):
        ref = peak_signal_noise_ratio(gt[b].numpy(), pred[b].numpy(), data_range=1.0)
        assert ours[b].item() == pytest.approx(ref, abs=1e-10)
    assert psnr(pred[0], gt[0]).shape == ()
    assert psnr(pred[0], gt[0]).item() == pytest.approx(ours[0].item(), abs=1e-12)


def test_masked_is_mse_over_masked_pixels_and_channels(pair):
    pred, gt = pair
    mask = torch.zeros(17, 23, dtype=torch.bool)
    mask[3:9, 5:20] = True
    err = ((pred - gt) ** 2).numpy()
    for b in range(2):
        expected = -10 * np.log10(err[b][:, mask.numpy()].mean())
        assert psnr(pred[b], gt[b], mask).item() == pytest.approx(expected, abs=1e-10)
        # the rectangle mask is the same as cropping
        crop = psnr(pred[b, :, 3:9, 5:20], gt[b, :, 3:9, 5:20])
        assert psnr(pred[b], gt[b], mask).item() == pytest.approx(crop.item(), abs=1e-10)


def test_mask_shapes_agree(pair):
    pred, gt = pair
    mask = torch.rand(17, 23, generator=torch.Generator().manual_seed(1)) > 0.5
    ref = psnr(pred, gt, mask)
    for m in (mask[None], mask.expand(2, 17, 23), mask[None, None], mask.expand(2, 1, 17, 23).float()):
        torch.testing.assert_close(psnr(pred, gt, m), ref)
    # a uniform soft weight is the unmasked PSNR
    torch.testing.assert_close(psnr(pred, gt, torch.full((17, 23), 0.5)), psnr(pred, gt))


def test_special_values(pair):
    pred, gt = pair
    assert math.isinf(psnr(gt, gt).max().item()) and (psnr(gt, gt) > 0).all()
    empty = torch.zeros(2, 17, 23, dtype=torch.bool)
    empty[1, 4, 4] = True
    values = psnr(pred, gt, empty)  # image 0: empty mask -> NaN; image 1: one pixel
    assert math.isnan(values[0].item()) and math.isfinite(values[1].item())
    assert math.isnan(mse(pred[0], gt[0], torch.zeros(17, 23)).item())


def test_bad_inputs(pair):
    pred, gt = pair
    with pytest.raises(ValueError, match="same shape"):
        psnr(pred, gt[:, :, :-1])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        psnr(pred, gt, torch.full((17, 23), 2.0))
    with pytest.raises(ValueError, match="does not fit"):
        psnr(pred, gt, torch.ones(16, 23))
    with pytest.raises(TypeError):
        psnr((pred * 255).to(torch.uint8), (gt * 255).to(torch.uint8))
