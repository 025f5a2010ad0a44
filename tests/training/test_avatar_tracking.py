"""A motion tracked by a frozen avatar (avatar.training.avatar_tracking): a known displacement of the meshes is pulled
back from the images, a part no view shows keeps the tracker's parameters, the avatar itself never moves."""

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
from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate
from avatar.templates import procedural_hand, procedural_head
from avatar.training.avatar_tracking import AvatarTrackingConfig, track_with_avatar
from avatar.training.rendering import rasterize

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
