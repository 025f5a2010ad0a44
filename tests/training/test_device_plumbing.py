"""The training loops make no tensor on a device nobody named: every tensor a step creates follows the data's device
(or names the host on purpose: the samplers' draws), so that with the model and the data on a GPU (``run.device``) no
step falls back to the CPU.

Without a GPU this is checked on the CPU with the default device set to ``meta``: the data stay on the CPU, and a
tensor created without naming its device lands on ``meta``, where the step then fails (a ``meta`` tensor mixed with a
CPU one, or read on the host). On a GPU that tensor would have been a CPU tensor in a CUDA step. The CUDA tests
(``tests/gpu``, ``make test-gpu``) check the real thing."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from avatar.device import fits_on_device
from avatar.metrics.evaluation import default_lpips
from avatar.metrics.lpips import LPIPS
from avatar.representations.bound.density import DensityController
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.representations.embedded.training import train_splatting
from avatar.templates import procedural_hand, procedural_head
from avatar.training.avatar_tracking import AvatarTrackingConfig, track_with_avatar
from avatar.training.checkpoint import placement
from avatar.training.frame_params import FrameParams, ParamLearningRates
from avatar.training.selection import SelectionConfig
from avatar.training.validation import ValidationConfig, Validator
from tests.representations.bound.conftest import TINY, Scene, make_scene, scene_params
from tests.representations.embedded.test_training import CFG as SPLATTING
from tests.representations.embedded.test_training import _model as splatting_model
from tests.representations.embedded.test_training import _scene as splatting_scene

HAND_X = [0.08, 1.0, 0.09, 0.5]


@contextlib.contextmanager
def unnamed_tensors_on_meta() -> Iterator[None]:
    """Tensors made without naming a device go to ``meta`` inside the block."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


@pytest.fixture(scope="module")
def four_frames() -> Scene:
    return make_scene(HAND_X)


@pytest.fixture(scope="module")
def vgg() -> LPIPS:
    return LPIPS("vgg").load_weights()


def _params(scene: Scene) -> FrameParams:
    head, hand = procedural_head(), procedural_hand()
    offsets = torch.zeros(len(HAND_X), scene.num_face_vertices, 3)
    return FrameParams(scene_params(HAND_X), head, hand, offsets, ParamLearningRates(), centred=True)


def _validator(scene: Scene) -> Validator:
    """Validation every 2 steps with LPIPS-alex, whose shared module is built (once, then moved to the data's device)
    before the check begins."""
    default_lpips().load_weights()
    return Validator(ValidationConfig(every=2, frames=1, lpips=True), scene.views)


def test_a_warmup_step_with_density_control_refinement_and_validation_names_its_devices(
    four_frames: Scene,
) -> None:
    scene = four_frames
    model = BoundGaussians.on_triangles(
        scene.meshes.vertices[0], scene.meshes.faces, scene.meshes.face_part, 1, init_opacity=0.3
    )
    params, validator = _params(scene), _validator(scene)
    cfg = WarmupTrainConfig(
        steps=6, densify_from=0.0, densify_until=1.0, densify_interval=0.34, log_every=1, backend="torch"
    )
    with unnamed_tensors_on_meta():
        log = train_warmup(model, scene.views, scene.meshes, cfg, validator=validator, params=params)
    assert len(log) == 6 and validator.curve


def test_a_stage_two_step_with_the_patch_loss_refinement_and_selection_names_its_devices(
    four_frames: Scene, vgg: LPIPS
) -> None:
    scene = four_frames
    model, params, validator = scene.model(TINY), _params(scene), _validator(scene)
    cfg = DynamicTrainConfig(
        steps=4, backend="torch", log_every=1, selection=SelectionConfig(enabled=True), patch_min_size=16
    )
    contact = np.array([True, False, True, False])
    with unnamed_tensors_on_meta():
        result = train_dynamic(
            model, scene.views, scene.meshes, scene.cond, contact, cfg, lpips=vgg, validator=validator, params=params
        )
    assert len(result.log) == 4 and result.selection is not None
    assert result.interaction_evaluations > 0  # the interaction MLPs ran in some step


def test_the_shared_heads_and_bf16_networks_name_their_devices(four_frames: Scene) -> None:
    model = four_frames.model(dataclasses.replace(TINY, heads="shared"))
    model.precision = "bf16"
    cfg = DynamicTrainConfig(steps=2, backend="torch", patch_weight=0.0, log_every=1)
    scene = four_frames
    with unnamed_tensors_on_meta():
        result = train_dynamic(model, scene.views, scene.meshes, scene.cond, np.ones(4, bool), cfg)
    assert len(result.log) == 2


def test_tracking_the_held_out_motion_with_the_avatar_names_its_devices(four_frames: Scene) -> None:
    scene = four_frames
    model = scene.model(TINY).requires_grad_(False)
    offsets = torch.zeros(len(HAND_X), scene.num_face_vertices, 3)
    head, hand = procedural_head(), procedural_hand()
    with unnamed_tensors_on_meta():
        tracked = track_with_avatar(
            model, scene_params(HAND_X), head, hand, offsets, scene.views, AvatarTrackingConfig(steps=2), "torch"
        )
    assert tracked.loss_after.shape == (len(HAND_X),)


def test_a_splatting_avatar_step_names_its_devices() -> None:
    views, meshes = splatting_scene()
    model = splatting_model(meshes)
    cfg = dataclasses.replace(SPLATTING, steps=4, lambda_lpips=0.0)
    with unnamed_tensors_on_meta():
        log = train_splatting(model, views, meshes, cfg)
    assert log


def test_the_probe_catches_a_tensor_made_without_its_device() -> None:
    """The check itself: a density controller made without naming the model's device (the bug this guards against)
    fails the step."""
    scene = make_scene(HAND_X)
    model = BoundGaussians.on_triangles(
        scene.meshes.vertices[0], scene.meshes.faces, scene.meshes.face_part, 1, init_opacity=0.3
    )
    grads, visible = torch.ones(model.num_gaussians), torch.ones(model.num_gaussians, dtype=torch.bool)
    with unnamed_tensors_on_meta(), pytest.raises(RuntimeError, match="meta tensors"):
        controller = DensityController(WarmupTrainConfig(steps=4).density(), model.num_gaussians)
        controller.accumulate(grads, visible, 32)
        float(controller.grad_sum.sum())


def test_a_capture_that_does_not_fit_the_gpu_is_one_error_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The crops may take half of the device's free memory (here 1 of 80 GiB free); the CPU is not checked."""
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (2**30, 80 * 2**30))
    fits_on_device(2**29, "cuda:0", "the crops", "lower quality.image_size")
    with pytest.raises(MemoryError) as caught:
        fits_on_device(2**29 + 1, "cuda:0", "the 24 frames x 7 cameras of train/train crops in F", "lower the size")
    said = str(caught.value)
    assert said.startswith("the 24 frames x 7 cameras of train/train crops in F take 0.50 GiB, more than the 0.50 GiB")
    assert said.endswith("; lower the size")
    fits_on_device(10**15, "cpu", "the crops", "-")


def test_on_the_cpu_a_move_returns_the_very_same_tensors(four_frames: Scene) -> None:
    views, meshes, cond = four_frames.views, four_frames.meshes, four_frames.cond
    assert views.to("cpu").images is views.images and meshes.to("cpu").vertices is meshes.vertices
    assert cond.to("cpu").face_offsets is cond.face_offsets


def test_a_checkpoint_resumed_on_another_card_loads_onto_the_run_s_card() -> None:
    """What was saved on a CUDA device goes to the run's (the cards of a machine share a cache entry, so a killed
    run may resume on another); what was saved on the CPU, the samplers' generator states, stays there."""

    class Storage:
        def __init__(self) -> None:
            self.moved_to: int | None = None

        def cuda(self, index: int) -> Storage:
            self.moved_to = index
            return self

    assert placement("cpu") is None  # the CPU: every tensor where it was saved
    on_card_1 = placement("cuda:1")
    assert on_card_1 is not None
    saved_on_0, saved_on_cpu = Storage(), Storage()
    assert on_card_1(saved_on_0, "cuda:0").moved_to == 1
    assert on_card_1(saved_on_cpu, "cpu") is saved_on_cpu and saved_on_cpu.moved_to is None
    assert placement("cuda")(Storage(), "cuda:3").moved_to == 0
