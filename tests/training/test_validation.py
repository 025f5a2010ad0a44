"""Validation during training: the flat-stop rule, the withheld frames, the curve of real (tiny) runs, the early
stop, and a killed run that resumes to the same curve and the same stop."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.geometry.views import ViewSet
from avatar.metrics.lpips import LPIPS
from avatar.posing import MeshSequence
from avatar.representations.bound import warmup
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.stage_two import DynamicTrainConfig, sample_frame, train_dynamic
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded.training import SplattingConfig, train_splatting
from avatar.training.validation import (
    FlatStop,
    ValidationConfig,
    Validator,
    is_flat,
    withheld_count,
    withheld_frames,
)
from pipeline.cli import run_app
from pipeline.config import ConfigError
from tests.conftest import compose_cfg
from tests.representations.bound.conftest import make_scene

WINDOW, MIN_GAIN = 3, 0.05


def _first_stop(curve: list[float], window: int = WINDOW, min_gain_db: float = MIN_GAIN) -> int | None:
    """How many validations the rule sees before it first stops (None: never)."""
    return next((n for n in range(1, len(curve) + 1) if is_flat(curve[:n], window, min_gain_db)), None)


def test_a_rising_curve_never_stops():
    assert _first_stop([20.0 + 0.5 * i for i in range(30)]) is None
    # best-so-far counts: dips below the best do not stop a curve whose best keeps rising
    assert _first_stop([20.0, 22.0, 21.0, 21.5, 22.2, 21.9, 22.5, 22.4, 22.8]) is None


def test_a_flat_curve_stops_after_window_validations_past_the_first():
    assert _first_stop([25.0] * 10) == WINDOW + 1
    assert _first_stop([25.0] * 10, window=1) == 2


def test_noise_below_the_threshold_stops_and_a_slow_climb_below_it_too():
    noise = 25.0 + 0.02 * np.random.default_rng(0).standard_normal(20)
    assert _first_stop(list(noise)) == WINDOW + 1
    assert _first_stop([25.0 + 0.01 * i for i in range(20)]) == WINDOW + 1
    # a rise, then a plateau: stops once the plateau has lasted a window
    assert _first_stop([20.0, 22.0, 24.0, 25.0, 25.01, 24.9, 25.02, 25.0]) == 7


def test_withheld_frames_are_evenly_spaced_deterministic_and_never_frame_zero():
    np.testing.assert_array_equal(withheld_frames(6, 4), [1, 2, 4, 5])
    np.testing.assert_array_equal(withheld_frames(24, 4), [5, 10, 14, 19])
    for t in range(2, 40):
        for count in range(1, t):
            frames = withheld_frames(t, count)
            assert len(set(frames.tolist())) == count and frames.min() >= 1 and frames.max() <= t - 1
    with pytest.raises(ValueError, match="at least one must stay for training"):
        withheld_frames(4, 4)


@pytest.mark.parametrize(
    ("frames", "fraction", "floor", "expected"),
    [
        (24, 0.15, 4, 4),  # draft's synthetic captures: 4 withheld, as before the fraction
        (8, 0.15, 4, 2),  # the short captures: 2 of 8
        (12, 0.15, 4, 2),
        (5, 0.15, 4, 1),
        (4, 0.15, 4, 0),  # nothing can be withheld: all four train
        (1, 0.15, 4, 0),
        (8, 0.25, 4, 2),  # ceil(2.0) is 2 whatever the float rounding of 0.25 * 8
        (8, 0.9, 4, 4),  # the floor bites: 4 stay
        (300, 0.15, 4, 45),  # the paper's captures: a fraction, not a count
    ],
)
def test_withheld_count_is_a_fraction_of_the_capture_with_a_floor_on_what_trains(frames, fraction, floor, expected):
    count = withheld_count(frames, fraction, floor)
    assert count == expected
    assert count == max(0, min(math.ceil(round(fraction * frames, 9)), frames - floor))  # the closed form
    if count:
        assert len(withheld_frames(frames, count)) == count


def test_a_limit_ends_training_at_the_chosen_step_with_the_planned_schedule(tmp_path: Path) -> None:
    """The retrain on every frame runs the validated run's schedule (planned over every step) to the chosen step:
    its first steps are those of the full run, bit for bit."""
    views, meshes = _scene(3)
    full = _model(meshes)
    log_full = train_warmup(full, views, meshes, CFG, validator=Validator(ValidationConfig(), views))
    limited = _model(meshes)
    validator = Validator(ValidationConfig(), views, limit=15)  # past the density control (until step 10)
    log = train_warmup(limited, views, meshes, CFG, validator=validator)
    assert validator.end == 15 and log[-1].step == 15
    assert [(r.step, r.loss) for r in log] == [(r.step, r.loss) for r in log_full if r.step <= 15]
    nothing = Validator(ValidationConfig(), views, limit=0)
    assert train_warmup(_model(meshes), views, meshes, CFG, validator=nothing) == [] and nothing.end == 0


def _scene(num_frames: int) -> tuple[ViewSet, MeshSequence]:
    """A red square (two triangles) 1 m in front of two 24 px cameras, over ``num_frames`` frames."""
    verts = torch.tensor([[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.2, 0.2, 0.0], [-0.2, 0.2, 0.0]])
    size, cams = 24, 2
    K = torch.tensor([[40.0, 0, size / 2 - 0.5], [0, 40.0, size / 2 - 0.5], [0, 0, 1]])
    w2c = torch.eye(4).repeat(cams, 1, 1)
    w2c[:, 2, 3] = 1.0
    w2c[1, 0, 3] = 0.05
    images = torch.zeros(num_frames, cams, size, size, 3, dtype=torch.uint8)
    images[..., 0] = 60
    images[:, :, 4:20, 4:20] = torch.tensor([220, 40, 40], dtype=torch.uint8)
    labels = torch.zeros(num_frames, cams, size, size, dtype=torch.uint8)
    labels[:, :, 4:20, 4:20] = 1
    views = ViewSet(images, labels, K.repeat(cams, 1, 1), w2c, ["a", "b"], torch.tensor([60 / 255, 0.0, 0.0]))
    meshes = MeshSequence(
        verts.repeat(num_frames, 1, 1),
        torch.tensor([[0, 1, 2], [0, 2, 3]]),
        torch.zeros(2, dtype=torch.long),
        ("face",),
    )
    return views, meshes


def _model(meshes: MeshSequence) -> BoundGaussians:
    return BoundGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 8, init_opacity=0.3)


# density control until step 10 of 40: the stop rule looks at the validations from step 10 on
CFG = WarmupTrainConfig(
    steps=40,
    densify_from=0.05,
    densify_until=0.25,
    densify_interval=0.125,
    opacity_reset_interval=1.0,
    log_every=5,
    checkpoint_every=10,
    lr_color=0.02,
    backend="torch",
)
STOP_NOW = FlatStop(enabled=True, min_gain_db=1e9, window=2)


def test_training_never_draws_a_withheld_frame(monkeypatch):
    views, meshes = _scene(6)
    validator = Validator(ValidationConfig(every=10, frames=2), views)
    drawn: list[tuple[int, bool]] = []
    real_render = warmup.render_frame

    def spy(model, meshes, views, frame, camera, backend="auto", vertices=None):
        drawn.append((frame, torch.is_grad_enabled()))
        return real_render(model, meshes, views, frame, camera, backend, vertices)

    monkeypatch.setattr(warmup, "render_frame", spy)
    train_warmup(_model(meshes), views, meshes, CFG, validator=validator)
    np.testing.assert_array_equal(validator.frames, [2, 4])
    trained = {f for f, grad in drawn if grad}
    assert trained == {0, 1, 3, 5}
    assert {f for f, grad in drawn if not grad} == {2, 4}
    # contact oversampling (stage two) draws from the training frames only, even when every contact is withheld
    gen = torch.Generator().manual_seed(0)
    contact = np.isin(np.arange(6), [2, 4])
    draws = {sample_frame(gen, validator.train_frames, contact, 1.0) for _ in range(300)}
    assert draws == {0, 1, 3, 5}


def test_a_tiny_warmup_records_a_curve_and_nothing_changes_without_validation():
    views, meshes = _scene(3)
    validator = Validator(ValidationConfig(every=10, frames=1), views)
    model = _model(meshes)
    log = train_warmup(model, views, meshes, CFG, validator=validator)
    steps = [p.step for p in validator.curve]
    assert steps == [0, 10, 20, 30, 40] and log[-1].step == 40
    psnrs = [p.psnr for p in validator.curve]
    assert all(math.isfinite(p) for p in psnrs) and psnrs[-1] > psnrs[0] + 1.0, psnrs
    walls = [p.wall_s for p in validator.curve]
    assert walls[0] == pytest.approx(0.0, abs=0.05) and walls == sorted(walls)
    table = validator.table()
    np.testing.assert_array_equal(table["step"], steps)
    m = validator.metrics()
    assert m["stopped_at_step"] == m["planned_steps"] == 40 and m["early_stopped"] is False
    assert m["validation_psnr"] == psnrs[-1] and m["validation_s"] > 0 and "time_saved_s" not in m

    off = Validator(ValidationConfig(), views)  # every=0: no frame withheld, no curve, the very same run as before
    plain, with_off = _model(meshes), _model(meshes)
    train_warmup(plain, views, meshes, CFG)
    train_warmup(with_off, views, meshes, CFG, validator=off)
    assert off.curve == [] and off.table()["step"].size == 0 and off.frames.size == 0
    for name, value in plain.state_dict().items():
        assert torch.equal(with_off.state_dict()[name], value), name


def test_lpips_on_the_curve_is_the_evaluation_metric_of_the_withheld_images_and_nan_when_off():
    """With ``lpips`` each point holds LPIPS-alex (``evaluate``'s metric) of the withheld frames from every training
    camera, computed here image by image from the renders; without it the column is NaN and no metric is written."""
    gen = torch.Generator().manual_seed(0)
    frames, cams, size = 5, 2, 40
    images = torch.randint(0, 256, (frames, cams, size, size, 3), generator=gen, dtype=torch.uint8)
    views = ViewSet(
        images,
        torch.zeros(frames, cams, size, size, dtype=torch.uint8),
        torch.eye(3).repeat(cams, 1, 1),
        torch.eye(4).repeat(cams, 1, 1),
        ["a", "b"],
        torch.zeros(3),
    )
    noise = torch.rand(frames, cams, size, size, 3, generator=gen)

    def render(frame: int) -> torch.Tensor:  # (C, S, S, 3): each frame's images, blurred towards noise
        return 0.7 * images[frame].float() / 255 + 0.3 * noise[frame]

    reference = LPIPS("alex")
    on, off = (Validator(ValidationConfig(every=1, frames=2, lpips=flag), views) for flag in (True, False))
    for validator in (on, off):
        validator.begin(0, 3, 0, render)
    np.testing.assert_array_equal(on.frames, [2, 3])
    expected = np.mean(
        [
            float(
                reference(render(t)[c].permute(2, 0, 1), images[t, c].permute(2, 0, 1).float() / 255, unit_range=True)
            )
            for t in (2, 3)
            for c in range(cams)
        ]
    )
    assert on.curve[0].lpips == pytest.approx(expected, rel=1e-5) and 0.0 < expected
    assert on.curve[0].psnr == off.curve[0].psnr
    assert on.metrics()["validation_lpips"] == on.curve[0].lpips
    assert math.isnan(off.curve[0].lpips) and "validation_lpips" not in off.metrics()
    assert math.isnan(off.table()["lpips"][0]) and on.table()["lpips"][0] == on.curve[0].lpips


@pytest.mark.parametrize(("densify_until", "stop"), [(0.25, 20), (0.5, 30)])
def test_a_flat_curve_stops_at_the_first_window_after_density_control(densify_until: float, stop: int):
    views, meshes = _scene(3)
    validator = Validator(ValidationConfig(every=5, frames=1, stop_when_flat=STOP_NOW), views)
    cfg = dataclasses.replace(CFG, densify_until=densify_until)
    log = train_warmup(_model(meshes), views, meshes, cfg, validator=validator)
    m = validator.metrics()
    assert validator.curve[-1].step == stop == m["stopped_at_step"] < m["planned_steps"] == 40
    assert log[-1].step == stop  # the last step run is logged
    assert m["early_stopped"] is True and m["time_saved_s"] > 0


def test_the_splatting_avatar_loop_records_its_curve_and_stops_after_its_density_control():
    views, meshes = _scene(3)
    model = EmbeddedGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 8, init_opacity=0.3)
    cfg = SplattingConfig(steps=40, lambda_lpips=0.0, densify_until=0.25, log_every=5, backend="torch")
    validator = Validator(ValidationConfig(every=5, frames=1, stop_when_flat=STOP_NOW), views)
    log = train_splatting(model, views, meshes, cfg, validator=validator)
    assert [p.step for p in validator.curve] == [0, 5, 10, 15, 20] and log[-1].step == 20
    assert all(math.isfinite(p.psnr) for p in validator.curve)


def _killed_at(step: int):  # a Progress that dies before ``step``
    def progress(steps):
        for s in steps:
            if s == step:
                raise KeyboardInterrupt("killed")
            yield s

    return progress


@pytest.mark.parametrize("kill_at", [17, 38])  # before the stop (checkpoint 10), after it (checkpoint 20, stopped)
def test_a_killed_run_resumes_the_curve_and_the_stop(tmp_path: Path, kill_at: int):
    views, meshes = _scene(3)
    config = ValidationConfig(every=5, frames=1, stop_when_flat=STOP_NOW)
    reference = _model(meshes)
    ref = Validator(config, views)
    ref_log = train_warmup(reference, views, meshes, CFG, validator=ref)
    assert ref.stopped_at == 20  # a checkpoint step: the checkpoint holds the stop

    if kill_at > ref.stopped_at:  # the stopped run was killed before the stage wrote its outputs
        train_warmup(_model(meshes), views, meshes, CFG, tmp_path, validator=Validator(config, views))
    else:
        with pytest.raises(KeyboardInterrupt):
            train_warmup(_model(meshes), views, meshes, CFG, tmp_path, _killed_at(kill_at), Validator(config, views))
    resumed = _model(meshes)
    again = Validator(config, views)
    log = train_warmup(resumed, views, meshes, CFG, tmp_path, validator=again)
    assert [(p.step, p.psnr) for p in again.curve] == [(p.step, p.psnr) for p in ref.curve]
    assert again.stopped_at == ref.stopped_at and [r.step for r in log] == [r.step for r in ref_log]
    for name, value in reference.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=1e-5, atol=1e-6)


def test_stage_two_records_a_curve_and_stops_at_the_first_window():
    scene = make_scene([0.08, 0.3, 1.0])  # frame 2 withheld (the hand far away); contact in frame 0
    contact = np.array([True, False, False])
    cfg = DynamicTrainConfig(steps=6, backend="auto", patch_weight=0.0, log_every=1)
    validator = Validator(ValidationConfig(every=1, frames=1, stop_when_flat=FlatStop(True, 1e9, 2)), scene.views)
    result = train_dynamic(scene.model(), scene.views, scene.meshes, scene.cond, contact, cfg, validator=validator)
    np.testing.assert_array_equal(validator.frames, [2])
    assert [p.step for p in validator.curve] == [0, 1, 2] and all(math.isfinite(p.psnr) for p in validator.curve)
    assert validator.metrics()["stopped_at_step"] == 2 and result.log[-1].step == 2


def test_bad_validation_settings_fail_before_any_stage(tmp_path: Path):
    overrides = [
        "stage.warmup.validation.every=-1",
        "stage.warmup.validation.stop_when_flat.window=0",
        "stage.dynamic.validation.min_train_frames=0",
        "stage.dynamic.validation.stop_when_flat.min_gain_db=nan",
    ]
    cfg = compose_cfg([f"paths.outputs={tmp_path / 'out'}", "run.progress=false", "run.dry=true", *overrides])
    with pytest.raises(ConfigError) as info:
        run_app(cfg)
    message = str(info.value)
    for expected in (
        "stage.warmup.validation.every=-1",
        "stage.warmup.validation.stop_when_flat.window=0",
        "stage.dynamic.validation.min_train_frames=0",
        "stage.dynamic.validation.stop_when_flat.min_gain_db=nan",
    ):
        assert expected in message, message
    assert not (tmp_path / "out").exists()
