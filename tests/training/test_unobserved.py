"""Crop padding (label UNOBSERVED: the crop reaches past the camera image) never reaches a loss or a metric:
in every training loop the render's padding pixels get no gradient (with the padding labelled background,
the old behaviour, they do), and validation and evaluation measure the observed pixels only."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest
import torch

from avatar.geometry.views import UNOBSERVED_LABEL, ViewSet
from avatar.metrics.lpips import LPIPS
from avatar.metrics.ssim import dssim_loss
from avatar.representations.bound import stage_two as dynamic
from avatar.representations.bound import warmup
from avatar.representations.embedded import training as splatting
from avatar.training.validation import ValidationConfig, Validator
from data_schemas.frames import UNOBSERVED
from stages.evaluate import _regions
from tests.representations.bound.conftest import make_scene
from tests.representations.embedded import test_training as splatting_case
from tests.training import test_warmup_training as static_case

BAND = 3  # padded columns on the left of every crop


def _padded(views: ViewSet, colour: int = 0, label: int = UNOBSERVED_LABEL) -> ViewSet:
    """``views`` with the first BAND columns of every crop holding ``colour`` and labelled ``label``."""
    images, labels = views.images.clone(), views.labels.clone()
    images[..., :BAND, :] = colour
    labels[..., :BAND] = label
    return dataclasses.replace(views, images=images, labels=labels)


def test_the_label_is_the_frames_schemas() -> None:
    assert UNOBSERVED_LABEL == UNOBSERVED


def test_the_render_on_unobserved_pixels_changes_neither_loss_nor_gradient() -> None:
    gen = torch.Generator().manual_seed(0)
    views = _padded(
        ViewSet(
            torch.randint(0, 256, (1, 1, 32, 32, 3), generator=gen, dtype=torch.uint8),
            torch.ones(1, 1, 32, 32, dtype=torch.uint8),
            torch.eye(3)[None],
            torch.eye(4)[None],
            ["a"],
            torch.zeros(3),
        )
    )
    first = torch.rand(32, 32, 3, generator=gen, dtype=torch.float64)
    second = first.clone()
    second[:, :BAND] = torch.rand(32, BAND, 3, generator=gen, dtype=torch.float64)
    results = []
    for values in (first, second):
        render = values.clone().requires_grad_()
        gt, pred = views.target_and_render(render, 0, 0)
        assert gt.dtype == pred.dtype == torch.float64
        loss = (pred - gt).abs().mean() + dssim_loss(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None])
        (grad,) = torch.autograd.grad(loss, render)
        assert not grad[:, :BAND].any()
        assert grad[:, BAND:].abs().sum(-1).gt(0).float().mean() > 0.9
        results.append((loss.item(), grad))
    assert results[0][0] == results[1][0]
    assert torch.equal(results[0][1], results[1][1])


def _padding_gradients(
    module: ModuleType, name: str, train: Callable[[], None], monkeypatch: pytest.MonkeyPatch
) -> tuple[float, float]:
    """Run ``train`` with ``module.name`` (the loop's renderer) recording the gradient of every training
    render; returns the largest |gradient| on the padded columns and on the others."""
    real, grads = getattr(module, name), []

    def recording(*args, **kwargs):
        result = real(*args, **kwargs)
        out = result[0] if isinstance(result, tuple) else result
        if out.rgb.requires_grad:
            out.rgb.register_hook(lambda g: grads.append(g.detach().abs()))
        return result

    monkeypatch.setattr(module, name, recording)
    train()
    monkeypatch.setattr(module, name, real)
    assert grads, "no training render was recorded"
    return max(float(g[:, :BAND].max()) for g in grads), max(float(g[:, BAND:].max()) for g in grads)


def _static_loop(label: int) -> Callable[[], None]:
    views, meshes = static_case._scene()
    cfg = dataclasses.replace(static_case.CFG, steps=6)
    return lambda: warmup.train_warmup(static_case._model(meshes), _padded(views, label=label), meshes, cfg)


def _splatting_loop(label: int) -> Callable[[], None]:
    views, meshes = splatting_case._scene()
    cfg = dataclasses.replace(splatting_case.CFG, steps=6)
    return lambda: splatting.train_splatting(splatting_case._model(meshes), _padded(views, label=label), meshes, cfg)


def _dynamic_loop(label: int) -> Callable[[], None]:
    scene = make_scene([0.08, 1.0])
    cfg = dynamic.DynamicTrainConfig(
        steps=3,
        backend="auto",
        patch_weight=0.1,
        patch_min_size=16,
        log_every=1,
        contact_fraction=1.0,
        max_contact_emphasis=1e9,
    )
    return lambda: dynamic.train_dynamic(
        scene.model(),
        _padded(scene.views, label=label),
        scene.meshes,
        scene.cond,
        np.array([True, False]),
        cfg,
        lpips=LPIPS("vgg"),
    )


LOOPS = {
    "static": (warmup, "render_frame", _static_loop),
    "dynamic": (dynamic, "rasterize", _dynamic_loop),
    "splatting": (splatting, "render_splatting", _splatting_loop),
}


@pytest.mark.parametrize("loop", list(LOOPS))
def test_no_training_loop_compares_the_render_with_padding(loop: str, monkeypatch) -> None:
    module, name, make = LOOPS[loop]
    padding, elsewhere = _padding_gradients(module, name, make(UNOBSERVED_LABEL), monkeypatch)
    assert padding == 0.0 and elsewhere > 0.0
    # the control: padding labelled background is compared with the render, so the render there is pulled
    padding, _ = _padding_gradients(module, name, make(0), monkeypatch)
    assert padding > 0.0


def test_validation_psnr_is_over_the_observed_pixels() -> None:
    views, _ = static_case._scene()
    render_value = torch.full((views.num_cameras, views.size, views.size, 3), 0.5)
    curve = []
    for colour in (0, 255):
        validator = Validator(ValidationConfig(every=1, frames=1), _padded(views, colour))
        validator.begin(0, 1, 0, lambda t: render_value)
        curve.append(validator.curve[0].psnr)
    assert curve[0] == curve[1]
    # and it equals the PSNR of the observed columns alone
    gt = views.images[validator.frames[0], :, :, BAND:].float() / 255
    mse = (render_value[:, :, BAND:] - gt).square().mean()
    assert curve[0] == pytest.approx(float(-10 * torch.log10(mse)), abs=1e-4)


def test_evaluation_regions_leave_the_padding_out() -> None:
    labels = np.ones((40, 40), np.uint8)
    labels[10:20, 10:30] = 2
    assert _regions(labels)["full"] is None  # a crop inside the image: every pixel
    labels[:, :BAND] = UNOBSERVED
    full = _regions(labels)["full"]
    assert full is not None and not full[:, :BAND].any() and full[:, BAND:].all()
