"""Hand articulation and placement from intuitive controls.

MANO joint order: 0 wrist, 1-3 index, 4-6 middle, 7-9 pinky, 10-12 ring,
13-15 thumb (proximal to distal). Local joint rotations of SMPL-family models
act about axes fixed in the rest-pose frame, so the flexion and abduction axes
are read off the rest skeleton of the template:

* finger direction ``u`` = middle MCP - wrist, lateral ``l`` = index MCP - pinky
  MCP, palm normal ``N = normalize(l x u)`` (the side the palm faces, for a right
  hand).
* a finger flexes about ``normalize(b x N)`` (``b`` its bone direction), which
  moves the tip towards the palm side; it spreads about ``N``, away from the
  middle finger.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar.templates.layers import MANOLayer, hand_frame

#: MANO joint chains (proximal to distal), in the order thumb, index, middle, ring, pinky.
FINGER_CHAINS = ((13, 14, 15), (1, 2, 3), (4, 5, 6), (10, 11, 12), (7, 8, 9))
#: Fingertip vertex order of TemplateModel.tip_vertex_ids (thumb .. pinky) matches FINGER_CHAINS.
MIDDLE = 2


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass(frozen=True)
class HandFrame:
    """Rest-pose axes of one shaped hand (all (3,) unit vectors, MANO space).

    Attributes:
        finger: wrist -> middle MCP direction.
        palm: palm normal (the side the palm faces).
        lateral: completes the right-handed frame ``finger x palm``.
        flex_axes: (15, 3) flexion axis of each joint 1..15 (row j-1 for joint j).
        spread_axes: (15, 3) abduction axis of each joint (zero except at the
            first joint of each non-middle finger), signed to spread away from
            the middle finger.
    """

    finger: np.ndarray
    palm: np.ndarray
    lateral: np.ndarray
    flex_axes: np.ndarray
    spread_axes: np.ndarray

    @staticmethod
    def from_joints(joints: np.ndarray) -> HandFrame:
        """Frame from rest joints (16, 3) of the shaped template."""
        finger, palm, lateral = hand_frame(joints).T
        flex = np.zeros((15, 3))
        spread = np.zeros((15, 3))
        children = {j: c for chain in FINGER_CHAINS for j, c in zip(chain[:-1], chain[1:])}
        for f, chain in enumerate(FINGER_CHAINS):
            for j in chain:
                start = joints[j]
                end = joints[children[j]] if j in children else 2 * joints[j] - joints[j - 1]
                bone = _unit(end - start)
                flex[j - 1] = _unit(np.cross(bone, palm))
            if f != MIDDLE:
                root = chain[0]
                away = joints[root] - joints[FINGER_CHAINS[MIDDLE][0]]
                sign = np.sign(np.dot(np.cross(palm, finger), away)) or 1.0
                spread[root - 1] = sign * palm
        return HandFrame(finger, palm, lateral, flex, spread)

    def articulate(self, curl: np.ndarray, spread: float) -> np.ndarray:
        """MANO hand_pose (45,) from per-finger curl (5,) radians per joint (thumb ..
        pinky; the distal joints bend 0.8x and 0.6x as much) and ``spread``
        radians of abduction."""
        pose = np.zeros((15, 3))
        falloff = (1.0, 0.8, 0.6)
        for f, chain in enumerate(FINGER_CHAINS):
            for k, j in enumerate(chain):
                pose[j - 1] = curl[f] * falloff[k] * self.flex_axes[j - 1]
                pose[j - 1] += spread * self.spread_axes[j - 1]
        return pose.reshape(45)


def orientation(frame: HandFrame, finger_dir: np.ndarray, palm_dir: np.ndarray) -> np.ndarray:
    """MANO global_orient (3,) axis-angle that turns the rest hand so its fingers
    point along ``finger_dir`` and its palm faces ``palm_dir`` (world, (3,); the
    finger direction is made orthogonal to the palm direction)."""
    palm = _unit(palm_dir)
    finger = _unit(finger_dir - np.dot(finger_dir, palm) * palm)
    target = np.stack([finger, palm, np.cross(finger, palm)], axis=1)
    rest = np.stack([frame.finger, frame.palm, frame.lateral], axis=1)
    return Rotation.from_matrix(target @ rest.T).as_rotvec()


def place(
    layer: MANOLayer,
    betas: np.ndarray,
    hand_pose: np.ndarray,
    global_orient: np.ndarray,
    contact: np.ndarray | int,
    target: np.ndarray,
) -> np.ndarray:
    """MANO transl (3,) that puts the hand's contact point on ``target`` (3,) world.

    Args:
        contact: a vertex index, or a (3,) direction: the hand's extreme vertex
            along it (its first point of contact when moving that way) is used.
    """
    out = layer(
        torch.as_tensor(betas[None]),
        torch.as_tensor(hand_pose[None]),
        torch.as_tensor(global_orient[None]),
        torch.zeros(1, 3, dtype=torch.float64),
    )
    verts = out.vertices[0].numpy()
    if isinstance(contact, np.ndarray):
        point = verts[np.argmax(verts @ contact)]
    else:
        point = verts[contact]
    return target - point
