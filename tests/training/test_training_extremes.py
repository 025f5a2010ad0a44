"""Training at the extremes: ten times every learning rate (the warm-up, and stage two's hand MLPs,
interaction MLPs, PointNet++, point features and Gaussians), and contact in every frame. Every parameter
and loss stays finite."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from tests.representations.bound.conftest import make_scene
from tests.training.test_validation import _scene


def _ten_times(cfg):  # a training config dataclass
    return dataclasses.replace(
        cfg,
        **{
            f.name: 10 * getattr(cfg, f.name)
            for f in dataclasses.fields(cfg)
            if f.name.startswith("lr_") and f.name != "lr_decay"
        },
    )


def _all_finite(module_tensors: list[torch.Tensor]) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in module_tensors)


def test_the_warmup_at_ten_times_the_learning_rates_stays_finite():
    views, meshes = _scene(3)
    model = BoundGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 8, init_opacity=0.3)
    cfg = _ten_times(
        WarmupTrainConfig(
            steps=60,
            densify_from=0.1,
            densify_until=0.5,
            densify_interval=0.1,
            opacity_reset_interval=1.0,
            log_every=5,
            checkpoint_every=0,
            backend="torch",
        )
    )
    assert cfg.lr_scale == 10 * WarmupTrainConfig.lr_scale
    log = train_warmup(model, views, meshes, cfg)
    assert all(math.isfinite(r.loss) for r in log)
    assert _all_finite([p.detach() for p in model.parameters()]) and model.num_gaussians > 0


def test_stage_two_at_ten_times_the_learning_rates_stays_finite():
    scene = make_scene([0.08, 0.3, 0.02])
    model = scene.model()
    cfg = _ten_times(DynamicTrainConfig(steps=12, backend="auto", log_every=1))
    assert cfg.lr_mlp == 10 * DynamicTrainConfig.lr_mlp and cfg.lr_decay == DynamicTrainConfig.lr_decay
    result = train_dynamic(model, scene.views, scene.meshes, scene.cond, np.array([True, False, True]), cfg)
    assert all(math.isfinite(r.loss) for r in result.log)
    assert _all_finite([t for t in model.network_state().values() if t.is_floating_point()])
    assert _all_finite([p.detach() for p in model.gaussians.parameters()])


def test_contact_in_every_frame_trains_every_module_and_stays_finite():
    """The hand pressed to the face in every frame: contact oversampling has nothing else to draw, I runs
    on every step, and everything stays finite."""
    scene = make_scene([0.02, 0.03, 0.02])
    model = scene.model()
    result = train_dynamic(
        model,
        scene.views,
        scene.meshes,
        scene.cond,
        np.ones(3, bool),
        DynamicTrainConfig(steps=8, backend="auto", log_every=1, contact_fraction=0.9),
    )
    assert result.interaction_steps == 8 and result.interaction_evaluations > 0
    assert all(math.isfinite(r.loss) for r in result.log)
    assert _all_finite([t for t in model.network_state().values() if t.is_floating_point()])
