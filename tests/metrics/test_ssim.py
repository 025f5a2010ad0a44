"""SSIM / D-SSIM against scikit-image (valid borders) and scipy (zero borders), gradients, extremes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from avatar.metrics import dssim_loss, ssim, ssim_map
from avatar.metrics.ssim import C1, C2, _blur, gaussian_window

SKIMAGE = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)


def _pair(
    shape: tuple[int, ...], seed: int = 0, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth-ish ground truth and a noisy prediction, both in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(shape, generator=g, dtype=torch.float64)
    pred = (0.8 * gt + 0.2 * torch.rand(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return pred.to(dtype), gt.to(dtype)


def _skimage(pred: torch.Tensor, gt: torch.Tensor) -> tuple[float, np.ndarray]:
    """skimage's mean SSIM and full map (H, W, C) of one (C, H, W) pair."""
    mean, smap = structural_similarity(
        pred.permute(1, 2, 0).double().numpy(), gt.permute(1, 2, 0).double().numpy(), full=True, **SKIMAGE
    )
    return float(mean), smap


@pytest.mark.parametrize("shape", [(3, 32, 32), (3, 23, 41), (1, 11, 11)])
def test_valid_mean_and_map_match_skimage(shape):
    pred, gt = _pair(shape)
    ref_mean, ref_map = _skimage(pred, gt)
    assert ssim(pred, gt).item() == pytest.approx(ref_mean, abs=1e-12)
    # the valid map is skimage's map without its 5-pixel (reflect-padded) border
    np.testing.assert_allclose(ssim_map(pred, gt).permute(1, 2, 0).numpy(), ref_map[5:-5, 5:-5], atol=1e-12)


def test_float32_close_to_skimage():
    pred, gt = _pair((2, 3, 40, 36), dtype=torch.float32)
    ours = ssim(pred, gt)
    for b in range(2):
        assert ours[b].item() == pytest.approx(_skimage(pred[b], gt[b])[0], abs=2e-5)


def test_masked_is_mean_of_map_over_mask():
    pred, gt = _pair((3, 30, 34))
    mask = torch.zeros(30, 34, dtype=torch.bool)
    mask[2:20, 10:33] = True
    _, ref_map = _skimage(pred, gt)
    # valid: the mask cropped like the map (window centres inside the mask)
    inner = mask.numpy()[5:-5, 5:-5]
    assert ssim(pred, gt, mask).item() == pytest.approx(ref_map[5:-5, 5:-5][inner].mean(), abs=1e-12)
    # zero padding: the map has the image's shape
    zmap = ssim_map(pred, gt, padding="zero")
    assert ssim(pred, gt, mask, padding="zero").item() == pytest.approx(zmap[:, mask].mean().item(), abs=1e-12)


def test_zero_padding_matches_scipy():
    """3DGS-style SSIM: zero-padded Gaussian statistics over the full image."""
    pred, gt = _pair((3, 19, 25))

    def blur(a: np.ndarray) -> np.ndarray:
        return gaussian_filter(a, sigma=1.5, truncate=3.5, mode="constant", cval=0.0)

    x, y = pred.numpy(), gt.numpy()
    maps = []
    for c in range(3):
        mx, my = blur(x[c]), blur(y[c])
        vx, vy, vxy = blur(x[c] ** 2) - mx**2, blur(y[c] ** 2) - my**2, blur(x[c] * y[c]) - mx * my
        maps.append((2 * mx * my + C1) * (2 * vxy + C2) / ((mx**2 + my**2 + C1) * (vx + vy + C2)))
    np.testing.assert_allclose(ssim_map(pred, gt, padding="zero").numpy(), np.stack(maps), atol=1e-12)
    assert dssim_loss(pred, gt).item() == pytest.approx(1 - np.mean(maps), abs=1e-12)


def test_constant_images():
    a = torch.full((3, 16, 16), 0.3, dtype=torch.float64)
    b = torch.full((3, 16, 16), 0.7, dtype=torch.float64)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-12)
    expected = (2 * 0.3 * 0.7 + C1) / (0.3**2 + 0.7**2 + C1)  # variances are 0
    assert ssim(a, b).item() == pytest.approx(expected, abs=1e-10)
    assert ssim(a, b).item() == pytest.approx(_skimage(a, b)[0], abs=1e-10)
    assert ssim(a, a, padding="zero").item() == pytest.approx(1.0, abs=1e-12)


def test_tiny_images():
    """Below 11 pixels there is no complete window: NaN for 'valid', defined with zero padding."""
    pred, gt = _pair((2, 3, 8, 12))
    assert ssim_map(pred, gt).shape == (2, 3, 0, 2)
    assert torch.isnan(ssim(pred, gt)).all()
    assert torch.isnan(ssim(pred, gt, torch.ones(8, 12))).all()
    one = _pair((3, 1, 1))
    assert torch.isfinite(ssim(*one, padding="zero"))
    pred.requires_grad_(True)
    loss = dssim_loss(pred, gt)
    loss.backward()
    assert 0 <= loss.item() <= 2 and torch.isfinite(pred.grad).all()


def test_gradcheck():
    mask = torch.rand(12, 13, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    # full Jacobian of the masked zero-padded loss on one small channel
    pred, gt = _pair((1, 1, 12, 13))
    pred.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: dssim_loss(p, gt, mask), (pred,))
    # 3 channels, valid borders: random projections of the Jacobian (fast mode)
    pred3, gt3 = _pair((2, 3, 12, 13))
    pred3.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt3), (pred3,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt3, mask), (pred3,), fast_mode=True)


def test_dssim_loss():
    pred, gt = _pair((2, 3, 20, 20))
    assert dssim_loss(gt, gt).item() == pytest.approx(0.0, abs=1e-12)
    # pooled over the batch: equal-size images -> mean of the per-image 1 - SSIM
    per_image = 1 - ssim(pred, gt, padding="zero")
    assert dssim_loss(pred, gt).item() == pytest.approx(per_image.mean().item(), abs=1e-12)
    assert dssim_loss(pred[0], gt[0]).item() == pytest.approx(per_image[0].item(), abs=1e-12)


def test_empty_mask():
    pred, gt = _pair((2, 3, 20, 20))
    empty = torch.zeros(20, 20)
    assert torch.isnan(ssim(pred, gt, empty)).all()
    pred.requires_grad_(True)
    loss = dssim_loss(pred, gt, empty)
    loss.backward()
    assert loss.item() == 0.0 and torch.equal(pred.grad, torch.zeros_like(pred))
    # constant inputs: finite gradients
    flat = torch.full((1, 3, 12, 12), 0.5, dtype=torch.float64, requires_grad=True)
    dssim_loss(flat, torch.zeros_like(flat)).backward()
    assert torch.isfinite(flat.grad).all() and not math.isnan(ssim(flat, flat).item())


@pytest.mark.parametrize("padding", ["zero", "valid"])
def test_blur_matches_a_brute_force_2d_window(padding):
    """The shifted-sum separable filter (and its hand-written adjoint) against a direct 11 x 11 sum."""
    x = torch.rand(2, 3, 17, 14, generator=torch.Generator().manual_seed(5), dtype=torch.float64, requires_grad=True)
    g = gaussian_window(torch.float64)
    window = g[:, None] * g[None, :]
    padded = torch.nn.functional.pad(x, (5, 5, 5, 5)) if padding == "zero" else x
    h, w = padded.shape[-2] - 10, padded.shape[-1] - 10
    reference = sum(window[i, j] * padded[..., i : i + h, j : j + w] for i in range(11) for j in range(11))
    blurred = _blur(x, padding)
    assert blurred.shape == reference.shape
    torch.testing.assert_close(blurred, reference, rtol=0, atol=1e-14)
    weights = torch.rand(reference.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    (grad,) = torch.autograd.grad((blurred * weights).sum(), x)
    (ref_grad,) = torch.autograd.grad((reference * weights).sum(), x)
    torch.testing.assert_close(grad, ref_grad, rtol=0, atol=1e-14)
