"""A motion tracked by a frozen avatar (avatar.training.avatar_tracking): a known displacement of the meshes is pulled
back from the images, a part no view shows keeps the tracker's parameters, the avatar itself never moves; what the
tracking computes once (the networks' products of the fixed per-Gaussian inputs, the posing of a batch of frames)
gives what running everything at every step gives."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch
from torch import Tensor

from avatar.dynamic.conditioning import FrameConditioning
from avatar.geometry.frames import place_gaussians, triangle_frames
from avatar.geometry.views import HAND_LABEL, ViewSet
from avatar.posing import posed_keypoints, posed_meshes
from avatar.representations import PosesRepeatedly, frame_pose
from avatar.representations.bound.dynamic_model import DynamicFrame
from avatar.representations.bound.representation import BoundAvatar
from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate
from avatar.templates import procedural_hand, procedural_head
from avatar.training.avatar_tracking import AvatarTrackingConfig, track_with_avatar
from avatar.training.frame_params import FrameParams
from avatar.training.rendering import rasterize
from tests.representations.bound.conftest import TINY, Scene, make_scene, scene_params

HEAD, HAND = procedural_head(), procedural_hand()
SIZE = 64


@functools.cache
def _capture() -> SyntheticCapture:
    return generate(SyntheticConfig(subject="synth_a", sequence="train", image_size=SIZE, num_frames=2, supersample=1))


def _params() -> dict[str, np.ndarray]:
    return {k: np.asarray(v, dtype=np.float32).copy() for k, v in _capture().params.items()}


@dataclass
class _Gaussians:
    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor


class _TexturedMesh:
    """A stand-in avatar: one flat Gaussian per triangle of the posed meshes, a fixed random colour each (texture
    that a photometric term can lock onto). Nothing of it requires a gradient."""

    def __init__(self) -> None:
        self.faces = posed_meshes(_params(), HEAD, HAND).faces
        count = self.faces.shape[0]
        gen = torch.Generator().manual_seed(0)
        self.colors = torch.rand(count, 3, generator=gen)
        self.local = torch.zeros(count, 3), torch.tensor([[0.7, 0.7, 0.05]]).expand(count, 3)
        self.quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(count, 4)

    def __call__(self, cond: FrameConditioning, vertices: Tensor) -> _Gaussians:
        binding = torch.arange(self.faces.shape[0])
        means, scales, quats = place_gaussians(triangle_frames(vertices, self.faces), binding, *self.local, self.quats)
        return _Gaussians(means, scales, quats, torch.full((len(means),), 0.95), self.colors)


def _views(avatar: _TexturedMesh, params: dict[str, np.ndarray], cameras: int = 4) -> ViewSet:
    """The avatar rendered with ``params`` from the capture's first ``cameras`` cameras (labels: the capture's)."""
    capture = _capture()
    cams = capture.cameras[:cameras]
    views = ViewSet(
        torch.zeros(2, cameras, SIZE, SIZE, 3, dtype=torch.uint8),
        torch.from_numpy(np.stack([capture.masks[c.camera_id] for c in cams], 1)),
        torch.tensor(np.stack([c.K for c in cams]), dtype=torch.float32),
        torch.tensor(np.stack([c.world_to_cam for c in cams]), dtype=torch.float32),
        [c.camera_id for c in cams],
        torch.tensor([0.5, 0.5, 0.5]),
    )
    meshes = posed_meshes(params, HEAD, HAND)
    with torch.no_grad():
        for t in range(2):
            for c in range(cameras):
                rgb = rasterize(avatar(None, meshes.vertices[t].float()), views, c).rgb  # type: ignore[arg-type]
                views.images[t, c] = (rgb.clamp(0, 1) * 255).round().to(torch.uint8)
    return views


def _shifted(
    params: dict[str, np.ndarray], face_mm: tuple[float, float, float], hand_mm: tuple[float, float, float]
) -> dict[str, np.ndarray]:
    """``params`` with every frame's face and hand translated by the given millimetres."""
    out = {k: v.copy() for k, v in params.items()}
    out["flame_transl"] = out["flame_transl"] + np.asarray(face_mm, dtype=np.float32) * 1e-3
    out["mano_transl"] = out["mano_transl"] + np.asarray(hand_mm, dtype=np.float32) * 1e-3
    return out


def _error_mm(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    pa, pb = posed_keypoints(a, HEAD, HAND), posed_keypoints(b, HEAD, HAND)
    return {
        p: 1e3 * float(np.linalg.norm(pa[f"{p}_vertices"] - pb[f"{p}_vertices"], axis=-1).mean())
        for p in ("face", "hand")
    }


def test_a_known_displacement_is_pulled_back_from_the_images():
    avatar, truth = _TexturedMesh(), _params()
    views = _views(avatar, truth)
    start = _shifted(truth, (4.0, -3.0, 2.0), (-5.0, 4.0, 3.0))
    before = _error_mm(start, truth)
    tracked = track_with_avatar(avatar, start, HEAD, HAND, None, views, AvatarTrackingConfig(steps=60))
    after = _error_mm(tracked.params, truth)
    # measured: face 5.39 -> 0.07 mm, hand 7.07 -> 0.16 mm (a 64 px crop's pixel is about 5 mm at the subject)
    assert after["face"] < 0.1 * before["face"] and after["hand"] < 0.1 * before["hand"], (before, after)
    assert (tracked.loss_after < tracked.loss_before).all()
    np.testing.assert_array_equal(tracked.params["flame_shape"], start["flame_shape"])  # never the identity
    np.testing.assert_array_equal(tracked.params["mano_shape"], start["mano_shape"])
    assert not any(tracked.held[p].any() for p in ("face", "hand"))
    # no step: the tracker's parameters, exactly
    unmoved = track_with_avatar(avatar, start, HEAD, HAND, None, views, AvatarTrackingConfig(steps=0))
    for k, v in start.items():
        np.testing.assert_array_equal(unmoved.params[k], v)


def test_a_part_no_view_shows_keeps_the_trackers_parameters():
    avatar, truth = _TexturedMesh(), _params()
    views = _views(avatar, truth)
    labels = views.labels.clone()
    labels[1][labels[1] == HAND_LABEL] = 0  # frame 1: no view shows the hand
    start = _shifted(truth, (3.0, 0.0, 0.0), (0.0, 4.0, 0.0))
    tracked = track_with_avatar(
        avatar, start, HEAD, HAND, None, replace(views, labels=labels), AvatarTrackingConfig(steps=10)
    )
    assert tracked.held["hand"].tolist() == [False, True] and not tracked.held["face"].any()
    for k in ("mano_global_orient", "mano_transl", "mano_hand_pose"):
        np.testing.assert_array_equal(tracked.params[k][1], start[k][1])  # held, bit for bit
    assert not np.array_equal(tracked.params["mano_transl"][0], start["mano_transl"][0])  # frame 0's hand moved
    assert not np.array_equal(tracked.params["flame_transl"][1], start["flame_transl"][1])  # the face still moved


def test_it_refuses_a_frame_count_mismatch_and_bad_settings():
    avatar, truth = _TexturedMesh(), _params()
    views = _views(avatar, truth, cameras=1)
    one_frame = {k: v[:1] for k, v in truth.items()}
    with pytest.raises(ValueError, match="1 frames of parameters but 2 of images"):
        track_with_avatar(avatar, one_frame, HEAD, HAND, None, views, AvatarTrackingConfig())
    bad = AvatarTrackingConfig(steps=-1, lr_pose=float("nan"), final_rate=0.0)
    problems = bad.problems()
    assert len(problems) == 3 and problems[0].startswith("steps=-1") and "lr_pose=nan" in problems[1]
    assert AvatarTrackingConfig().problems() == []


def _tiny_avatar(heads: str) -> tuple[BoundAvatar, Scene]:
    """InteractAvatar's model at tiny widths on two frames with the hand at the cheek (H, I and PointNet++ all run),
    its output layers drawn at random as a trained model's would be (nonzero deltas), frozen."""
    scene = make_scene([0.08, 0.07])
    model = scene.model(replace(TINY, heads=heads))
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for module in (model.hand_geo, model.hand_app, model.interaction):
            for layer in module.output_layers():
                layer.weight.normal_(0.0, 0.1, generator=gen)
                layer.bias.normal_(0.0, 0.1, generator=gen)
    model.requires_grad_(False)
    return BoundAvatar(model), scene


def _per_step_reference(
    avatar: BoundAvatar, params: dict[str, np.ndarray], views: ViewSet, config: AvatarTrackingConfig
) -> dict[str, np.ndarray]:
    """The tracking with nothing computed once: one frame after the other, every step posing the frame twice
    (conditioning, vertices) and running the whole model."""
    frames = FrameParams(params, HEAD, HAND, None, config.rates())
    decay = config.final_rate ** (1 / max(config.steps - 1, 1))
    for t in range(frames.num_frames):
        for step in range(config.steps):
            gaussians = avatar.pose(frames.conditioning(t).as_sequence(), frames.vertices(t), 0)
            loss = sum(
                (render - gt).abs().mean()
                for gt, render in (
                    views.target_and_render(rasterize(gaussians, views, c).rgb, t, c) for c in range(views.num_cameras)
                )
            )
            (loss / views.num_cameras).backward()
            frames.optimizer.step(t, lr_scale=decay**step)
    return frames.arrays()


@pytest.mark.parametrize("heads", ["per_parameter", "shared"])
def test_the_reused_products_give_the_per_step_gaussians_and_gradients(heads: str):
    """Posing a batch of frames once and the networks' products of the fixed per-Gaussian inputs computed once
    (frame_pose): the same Gaussians and the same gradients in the frames' parameters as posing each frame twice
    and running the whole model, to float32 rounding."""
    avatar, scene = _tiny_avatar(heads)
    assert isinstance(avatar, PosesRepeatedly)  # frame_pose takes the bound avatar's own, with the products
    params = scene_params([0.08, 0.07])

    def run(reuse: bool) -> tuple[list[DynamicFrame], dict[str, Tensor]]:
        frames = FrameParams(params, HEAD, HAND, None, AvatarTrackingConfig().rates())
        if reuse:
            pose, (vertices, cond) = frame_pose(avatar), frames.posed(slice(0, 2))
            posed = [pose(cond.frame(t), vertices[t]) for t in range(2)]
        else:
            posed = [avatar.pose(frames.conditioning(t).as_sequence(), frames.vertices(t), 0) for t in range(2)]
        sum(rasterize(g, scene.views, 0).rgb.square().sum() for g in posed).backward()
        return posed, {k: p.grad for k, p in frames.rows.items()}

    (reused, grads), (reference, grads_ref) = run(True), run(False)
    assert all(g.interaction_evaluations > 0 for g in reference)  # I ran: its products are covered
    for ours, ref in zip(reused, reference):
        assert ours.interaction_evaluations == ref.interaction_evaluations
        for name in ("means", "scales", "quats", "opacities", "colors"):
            torch.testing.assert_close(getattr(ours, name), getattr(ref, name), rtol=1e-5, atol=1e-6)
    for name, grad in grads_ref.items():
        torch.testing.assert_close(grads[name], grad, rtol=1e-4, atol=1e-4 * float(grad.abs().max()))


def test_tracking_with_the_reuse_matches_the_per_step_tracking():
    """The tracking as evaluate runs it (frames in lockstep, frame_pose) against the per-step reference: the same
    refined meshes and losses. Not bit for bit: the rounding of a step's render moves a parameter that the images
    hardly constrain by up to Adam's rate (its update is about the rate times the gradient's sign), as running the
    reference itself on another number of threads does."""
    avatar, scene = _tiny_avatar("per_parameter")
    params = scene_params([0.08, 0.07])
    config = AvatarTrackingConfig(steps=10)
    tracked = track_with_avatar(frame_pose(avatar), params, HEAD, HAND, None, scene.views, config)
    reference = _per_step_reference(avatar, params, scene.views, config)
    moved, apart = _error_mm(reference, params), _error_mm(tracked.params, reference)
    # measured: the meshes moved 12.1 mm (face) and 7.4 mm (hand), and lie 0.001 and 0.003 mm apart
    assert min(moved.values()) > 5.0 and max(apart.values()) < 0.02, (moved, apart)
    for k, v in reference.items():  # rotations, poses (rad), expressions: measured within 6e-5
        np.testing.assert_allclose(tracked.params[k], v, rtol=0, atol=1e-3, err_msg=k)
