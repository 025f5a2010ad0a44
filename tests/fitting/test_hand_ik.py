"""Inverse kinematics from 3D hand keypoints, against the forward model."""

from __future__ import annotations

import numpy as np
import torch

from avatar.fitting.hand_ik import bone_children, hand_pose_ik
from avatar.fitting.models import HandParams
from avatar.templates import MANOLayer, procedural_hand

HAND = procedural_hand()
MANO = MANOLayer(HAND)


def _keypoints(pose: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posed keypoints (T, 21, 3) and joints (T, 16, 3) of the mean shape."""
    T = pose.shape[0]
    out = MANO(
        torch.zeros(T, 10, dtype=torch.float64), torch.as_tensor(pose), torch.as_tensor(orient), torch.as_tensor(transl)
    )
    return MANO.keypoints21(out.vertices, out.joints).numpy(), out.joints.numpy()


def _rest() -> tuple[np.ndarray, np.ndarray]:
    out = MANO(torch.zeros(1, 10, dtype=torch.float64), torch.zeros(1, 45, dtype=torch.float64))
    return out.joints[0].numpy(), out.vertices[0, MANO.tip_vertex_ids].numpy()


def test_every_bone_points_at_one_child() -> None:
    children = bone_children(MANO.parents)
    assert sorted(children) == list(range(1, 16))
    assert sorted(children.values()) == sorted(set(range(2, 21)) - {4, 7, 10, 13})  # joints past the MCPs + 5 tips


def test_ik_reproduces_the_joints_of_a_bent_twisted_hand() -> None:
    """Joint positions only constrain bone directions; twist is free, so compare keypoints, not angles."""
    rng = np.random.default_rng(0)
    T = 5
    pose = rng.normal(0.0, 0.5, (T, 45))
    pose[-1] = np.tile([0.0, 0.0, 1.55], 15)  # fully bent fingers
    orient, transl = rng.normal(0.0, 1.0, (T, 3)), rng.normal(0.0, 0.2, (T, 3))
    target, joints = _keypoints(pose, orient, transl)
    rest_joints, rest_tips = _rest()
    o, t, p, ok = hand_pose_ik(rest_joints, rest_tips, MANO.parents, target, np.ones((T, 21), bool))
    assert ok.all()
    ik_kp, ik_joints = _keypoints(p, o, t)
    np.testing.assert_allclose(ik_joints, joints, atol=1e-9)  # joints depend on rotations only: exact
    # Fingertips are skin vertices, moved a little by pose correctives: sub-millimetre.
    assert np.abs(ik_kp - target).max() < 1e-3


def test_missing_keypoints_leave_bones_at_rest_and_frames_without_a_palm_not_ok() -> None:
    target, _ = _keypoints(np.full((2, 45), 0.3), np.zeros((2, 3)), np.zeros((2, 3)))
    valid = np.ones((2, 21), bool)
    valid[0, 8] = False  # index fingertip unseen: the last index bone stays straight
    valid[1, [0, 1, 5, 9, 13, 17]] = False  # frame 1 has no palm at all
    o, t, p, ok = hand_pose_ik(*_rest(), MANO.parents, target, valid)
    assert ok.tolist() == [True, False]
    index_last = 3  # MANO joint 3 = index distal; its rotation is hand_pose[:, 6:9]
    np.testing.assert_array_equal(p[0, 3 * (index_last - 1) : 3 * index_last], 0.0)
    assert np.isfinite(p).all() and np.isfinite(o).all() and np.isfinite(t).all()


def test_hand_params_fill_frames_without_a_palm_from_neighbours() -> None:
    target, _ = _keypoints(np.full((3, 45), 0.2), np.zeros((3, 3)), np.tile([0.0, 0.0, 0.5], (3, 1)))
    valid = np.ones((3, 21), bool)
    valid[1] = False
    params = HandParams(HAND, 3)
    ok = params.init_from_keypoints(target, valid)
    assert ok.tolist() == [True, False, True]
    np.testing.assert_array_equal(params.hand_pose[1].detach().numpy(), params.hand_pose[0].detach().numpy())
    with torch.no_grad():
        fitted = params.keypoints().numpy()
    assert np.abs(fitted - target).max() < 1e-3
