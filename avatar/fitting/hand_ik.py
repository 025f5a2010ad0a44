"""Analytic inverse kinematics: MANO pose from 3D hand keypoints.

The starting point of the hand fit. Flat-hand starts left bent fingers (contact
frames) in local minima of the reprojection loss (20-40 mm MPJPE); bone
directions from triangulated keypoints put every finger in the right basin.

Method: the wrist rotation is the Kabsch alignment of the rest-pose palm
(the wrist and the five joints attached to it, whose positions depend on the
global rotation only) to their triangulated positions. Then, down each finger,
a joint's local rotation is the smallest rotation that turns its rest bone
(joint to child joint, or to the fingertip) onto the observed bone direction,
expressed in the parent's posed frame. Twist about a bone is unobservable from
keypoints and stays zero; a bone whose end points were not triangulated keeps
a zero rotation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from avatar.fitting.rigid import MIN_RIGID_POINTS, kabsch, smallest_rotation
from avatar.templates.layers import MANO_NUM_JOINTS, OPENPOSE_FROM_MANO

#: Fingertip (index into the 5 tips, in OPENPOSE_FROM_MANO's [joints, tips] layout)
#: beyond the last joint of each MANO finger: index 3, middle 6, pinky 9, ring 12, thumb 15.
TIP_AFTER_JOINT = {3: 17, 6: 18, 9: 20, 12: 19, 15: 16}


def bone_children(parents: list[int]) -> dict[int, int]:
    """Joint -> the point its bone points at, in [16 joints, 5 tips] indexing.

    Every MANO joint other than the wrist has one child joint, or a fingertip.
    """
    children: dict[int, int] = {}
    for j in range(1, MANO_NUM_JOINTS):
        kids = [k for k in range(MANO_NUM_JOINTS) if parents[k] == j]
        children[j] = kids[0] if kids else TIP_AFTER_JOINT[j]
    return children


def hand_pose_ik(
    rest_joints: np.ndarray, rest_tips: np.ndarray, parents: list[int], targets: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame MANO rotations from 3D keypoints.

    Args:
        rest_joints: (16, 3) MANO joints of the rest pose (the current shape), metres.
        rest_tips: (5, 3) fingertip vertices of the rest pose (thumb, index, middle, ring, pinky).
        parents: the 16 parent indices of the kinematic tree (-1 for the wrist).
        targets: (T, 21, 3) keypoints in OpenPose order, metres; valid: (T, 21) bool.

    Returns:
        global_orient (T, 3) axis-angle about the wrist, transl (T, 3) so that
        the layer's posed wrist lands where Kabsch puts it, hand_pose (T, 45)
        axis-angle of joints 1..15, ok (T,) frames whose palm had >= 3 valid
        points (the others are zero; the caller fills them from neighbours).
    """
    order = np.asarray(OPENPOSE_FROM_MANO)
    rest = np.concatenate((rest_joints, rest_tips))  # (21, 3) in [joints, tips] layout
    children = bone_children(parents)
    palm = [0] + [k for k in range(MANO_NUM_JOINTS) if parents[k] == 0]
    T = targets.shape[0]
    orient, transl, pose = np.zeros((T, 3)), np.zeros((T, 3)), np.zeros((T, MANO_NUM_JOINTS - 1, 3))
    ok = np.zeros(T, bool)
    for t in range(T):
        points = np.zeros((len(rest), 3))
        seen = np.zeros(len(rest), bool)
        points[order], seen[order] = targets[t], valid[t]
        use = [k for k in palm if seen[k]]
        if len(use) < MIN_RIGID_POINTS:
            continue
        ok[t] = True
        R0, shift = kabsch(rest[use], points[use])
        orient[t] = Rotation.from_matrix(R0).as_rotvec()
        transl[t] = shift + R0 @ rest_joints[0] - rest_joints[0]
        frames = {0: R0}
        posed = {k: R0 @ rest[k] + shift for k in palm}
        for j in range(1, MANO_NUM_JOINTS):  # MANO lists every parent before its children
            parent_rot = frames[parents[j]]
            if j not in posed:
                posed[j] = posed[parents[j]] + parent_rot @ (rest[j] - rest[parents[j]])
            child = children[j]
            local = np.eye(3)
            if seen[child]:
                observed = points[child] - posed[j]
                if np.linalg.norm(observed) > 1e-9:
                    local = smallest_rotation(rest[child] - rest[j], parent_rot.T @ observed)
            frames[j] = parent_rot @ local
            pose[t, j - 1] = Rotation.from_matrix(local).as_rotvec()
    return orient, transl, pose.reshape(T, -1), ok
