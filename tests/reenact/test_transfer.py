"""Motion transfer against closed forms: identity when driving oneself, the hand-to-head transform kept (its
translation scaled by the head sizes), the target's shape and place kept, bad drivers refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.reenact import MotionTransferError, head_size, transfer_motion
from avatar.templates import procedural_hand, procedural_head
from avatar.templates.lbs import batch_rodrigues
from avatar.training.posing import pose_layers

HEAD, HAND = procedural_head(), procedural_hand()


def _params(seed: int, frames: int = 4, shape_scale: float = 1.0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = lambda *shape, s=0.1: rng.normal(0, s, shape)  # noqa: E731
    return {
        "flame_shape": np.repeat(n(1, 10, s=shape_scale), frames, 0), "flame_expression": n(frames, 10, s=0.5),
        "flame_global_orient": n(frames, 3), "flame_neck_pose": n(frames, 3), "flame_jaw_pose": n(frames, 3, s=0.05),
        "flame_eye_pose": n(frames, 6, s=0.05), "flame_transl": n(frames, 3, s=0.02) + [0.0, 0.0, 0.5],
        "mano_shape": np.repeat(n(1, 10, s=shape_scale), frames, 0), "mano_hand_pose": n(frames, 45, s=0.2),
        "mano_global_orient": n(frames, 3, s=0.5), "mano_transl": n(frames, 3, s=0.02) + [0.05, -0.02, 0.45],
    }


def _relative(params: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_rel (T, 3, 3), t_rel (T, 3) in the head frame, head roots (T, 3)) of posed parameters."""
    _, face, _, hand = pose_layers(params, HEAD, HAND, torch.float64)
    R_head = batch_rodrigues(torch.from_numpy(np.asarray(params["flame_global_orient"], np.float64))).numpy()
    R_hand = batch_rodrigues(torch.from_numpy(np.asarray(params["mano_global_orient"], np.float64))).numpy()
    root, wrist = face.joints[:, 0].numpy(), hand.joints[:, 0].numpy()
    return np.swapaxes(R_head, 1, 2) @ R_hand, np.einsum("tji,tj->ti", R_head, wrist - root), root


def test_driving_oneself_changes_nothing():
    params = _params(0)
    out, scale = transfer_motion(params, params, HEAD, HAND)
    assert scale == pytest.approx(1.0)
    for key, value in params.items():
        np.testing.assert_allclose(out[key], value, atol=1e-9, err_msg=key)


def test_another_actor_keeps_its_shape_and_place_and_the_driver_s_hand_to_head_transform():
    target, driver = _params(1, frames=3, shape_scale=2.0), _params(2, frames=5, shape_scale=2.0)
    out, scale = transfer_motion(target, driver, HEAD, HAND)
    assert len(out["flame_global_orient"]) == 5
    np.testing.assert_allclose(out["flame_shape"], np.repeat(target["flame_shape"][:1], 5, 0))
    np.testing.assert_allclose(out["mano_shape"], np.repeat(target["mano_shape"][:1], 5, 0))
    for key in ("flame_expression", "flame_jaw_pose", "mano_hand_pose", "flame_global_orient"):
        np.testing.assert_array_equal(out[key], driver[key])
    R_out, t_out, root_out = _relative(out)
    R_drv, t_drv, root_drv = _relative(driver)
    np.testing.assert_allclose(R_out, R_drv, atol=1e-9)  # the hand's rotation relative to the head
    np.testing.assert_allclose(t_out, scale * t_drv, atol=1e-9)  # its offset, scaled by the head sizes
    np.testing.assert_allclose(root_out[0], _relative(target)[2][0], atol=1e-9)  # the target stays in place
    np.testing.assert_allclose(root_out - root_out[0], root_drv - root_drv[0], atol=1e-9)  # moving as the driver
    sizes = [head_size(pose_layers({k: v[:1] for k, v in p.items()}, HEAD, HAND, torch.float64)[1].vertices[0].numpy())
             for p in (target, driver)]
    assert scale == pytest.approx(sizes[0] / sizes[1]) and abs(scale - 1.0) > 1e-3


def test_head_size_is_rotation_invariant_and_scales_linearly():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(50, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    assert head_size(points @ q.T + 5.0) == pytest.approx(head_size(points))
    assert head_size(2.5 * points) == pytest.approx(2.5 * head_size(points))


def test_bad_drivers_are_refused_with_the_reason():
    target = _params(4)
    with pytest.raises(MotionTransferError, match="no frames"):
        transfer_motion(target, {k: v[:0] for k, v in target.items()}, HEAD, HAND)
    broken = _params(5)
    broken["mano_hand_pose"][2, 7] = np.nan
    with pytest.raises(MotionTransferError, match=r"'mano_hand_pose' is not finite in frames \[2\]"):
        transfer_motion(target, broken, HEAD, HAND)
    other = _params(6)
    other["flame_expression"] = np.zeros((4, 50))
    with pytest.raises(MotionTransferError, match="different templates"):
        transfer_motion(target, other, HEAD, HAND)
