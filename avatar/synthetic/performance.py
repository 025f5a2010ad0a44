"""Evaluate a :class:`~avatar.synthetic.motion.Script` into per-frame FLAME and
MANO parameters (the ground truth of the capture) and the posed meshes.

Head: Euler angles split between FLAME's global orientation (30 %) and its
neck (70 %); jaw opening about the x axis; a smile and a brow-raise
expression coefficient. Hand: each frame blends the placements of the two
bracketing keys, both computed against the *current* posed face, so the hand
follows the head; articulation blends linearly, orientation by slerp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation, Slerp

from avatar.synthetic.face_anchors import FaceAnchors
from avatar.synthetic.geometry import vertex_normals
from avatar.synthetic.hand_pose import HandFrame, orientation, place
from avatar.synthetic.identity import Identity
from avatar.synthetic.motion import HandKey, Script, bracket
from avatar.templates.layers import FLAMELayer, MANOLayer

GLOBAL_SHARE = 0.3
#: Expression columns driven by HeadKey.smile and HeadKey.brow.
SMILE_COLUMN = 0
BROW_COLUMN = 4
FINGERS = ("thumb", "index", "middle", "ring", "pinky")


@dataclass
class Performance:
    """Per-frame parameters (float64, T rows) and posed meshes.

    Attributes:
        params: the SyntheticCapture.params dictionary.
        face_vertices: (T, Vf, 3) posed FLAME vertices (before soft-tissue offsets).
        hand_vertices: (T, Vh, 3) posed MANO vertices.
        hand_joints: (T, 16, 3) posed MANO joints.
        curl: (T, 5) finger curl controls (thumb .. pinky), radians.
    """

    params: dict[str, np.ndarray]
    face_vertices: np.ndarray
    hand_vertices: np.ndarray
    hand_joints: np.ndarray
    curl: np.ndarray


def _lerp(a: npt.ArrayLike, b: npt.ArrayLike, s: float) -> np.ndarray:
    return (1 - s) * np.asarray(a, dtype=np.float64) + s * np.asarray(b, dtype=np.float64)


def head_params(script: Script, times: np.ndarray, identity: Identity, num_expression: int) -> dict[str, np.ndarray]:
    """FLAME parameters (T rows) of the head track at ``times``."""
    keys = script.head
    key_times = np.array([k.time for k in keys])
    t_count = times.shape[0]
    out = {
        name: np.zeros((t_count, width))
        for name, width in (
            ("flame_expression", num_expression),
            ("flame_global_orient", 3),
            ("flame_neck_pose", 3),
            ("flame_jaw_pose", 3),
            ("flame_eye_pose", 6),
            ("flame_transl", 3),
        )
    }
    out["flame_shape"] = np.tile(identity.flame_shape, (t_count, 1))
    for f, t in enumerate(times):
        i, j, s = bracket(key_times, t)
        a, b = keys[i], keys[j]
        yaw, pitch, roll = (_lerp(getattr(a, n), getattr(b, n), s) for n in ("yaw_deg", "pitch_deg", "roll_deg"))
        # Yaw about +y (towards the subject's left), pitch about +x (looks down), roll about +z.
        rot = Rotation.from_euler("YXZ", [yaw, pitch, -roll], degrees=True).as_rotvec()
        out["flame_global_orient"][f] = GLOBAL_SHARE * rot
        out["flame_neck_pose"][f] = (1 - GLOBAL_SHARE) * rot
        out["flame_jaw_pose"][f, 0] = np.deg2rad(_lerp(a.jaw_deg, b.jaw_deg, s))
        # The eyes partly counter-rotate the head's yaw (keep looking ahead).
        out["flame_eye_pose"][f, [1, 4]] = -0.5 * np.deg2rad(yaw)
        if num_expression > max(SMILE_COLUMN, BROW_COLUMN):
            out["flame_expression"][f, SMILE_COLUMN] = _lerp(a.smile, b.smile, s)
            out["flame_expression"][f, BROW_COLUMN] = _lerp(a.brow, b.brow, s)
    return out


def _as_t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)


def pose_face(layer: FLAMELayer, params: dict[str, np.ndarray]) -> np.ndarray:
    """(T, Vf, 3) posed FLAME vertices for the head parameters."""
    out = layer(
        *(
            _as_t(params[k])
            for k in (
                "flame_shape",
                "flame_expression",
                "flame_global_orient",
                "flame_neck_pose",
                "flame_jaw_pose",
                "flame_eye_pose",
                "flame_transl",
            )
        )
    )
    return out.vertices.numpy()


class HandPlacer:
    """Turns hand keys into MANO parameters against a posed face."""

    def __init__(self, layer: MANOLayer, identity: Identity, anchors: FaceAnchors, face_faces: np.ndarray) -> None:
        self.layer = layer
        self.betas = identity.mano_shape
        rest = layer(_as_t(self.betas[None]), torch.zeros(1, 45, dtype=torch.float64))
        self.frame = HandFrame.from_joints(rest.joints[0].numpy())
        self.anchors = anchors
        self.face_faces = torch.from_numpy(np.array(face_faces))
        if layer.model.tip_vertex_ids is None:
            raise ValueError("the hand template has no tip_vertex_ids")
        self.tips = layer.model.tip_vertex_ids

    def _placement(
        self, key: HandKey, hand_pose: np.ndarray, face: np.ndarray, normals: np.ndarray, head_rot: Rotation
    ) -> tuple[Rotation, np.ndarray]:
        vid = self.anchors.vertex(key.anchor)
        point, normal = face[vid], normals[vid]
        finger_dir = head_rot.apply(np.asarray(key.finger_dir, dtype=np.float64))
        rot = Rotation.from_rotvec(orientation(self.frame, finger_dir, -normal))
        lateral = rot.apply(self.frame.lateral)
        rot = Rotation.from_rotvec(-np.deg2rad(key.tilt_deg) * lateral) * rot
        target = point + key.standoff_m * normal + head_rot.apply(np.asarray(key.shift_m, dtype=np.float64))
        contact: np.ndarray | int = -normal if key.contact == "extreme" else int(self.tips[FINGERS.index(key.contact)])
        transl = place(self.layer, self.betas, hand_pose, rot.as_rotvec(), contact, target)
        return rot, transl

    def frame_params(
        self, a: HandKey, b: HandKey, s: float, face: np.ndarray, head_rot: Rotation
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Blend keys a -> b by s at one frame: hand_pose (45,), global_orient (3,),
        transl (3,), curl (5,)."""
        curl = _lerp(a.curl, b.curl, s)
        hand_pose = self.frame.articulate(curl, float(_lerp(a.spread, b.spread, s)))
        normals = vertex_normals(_as_t(face), self.face_faces).numpy()
        rot_a, tr_a = self._placement(a, hand_pose, face, normals, head_rot)
        rot_b, tr_b = self._placement(b, hand_pose, face, normals, head_rot)
        rots = Rotation.from_quat(np.stack([rot_a.as_quat(), rot_b.as_quat()]))
        rot = Slerp([0.0, 1.0], rots)([s])[0]
        return hand_pose, rot.as_rotvec(), _lerp(tr_a, tr_b, s), curl


def perform(
    script: Script, times: np.ndarray, identity: Identity, flame: FLAMELayer, mano: MANOLayer, anchors: FaceAnchors
) -> Performance:
    """Evaluate the script at ``times`` (T,) into parameters and posed meshes."""
    params = head_params(script, times, identity, flame.num_expression)
    faces = pose_face(flame, params)
    placer = HandPlacer(mano, identity, anchors, flame.model.faces)
    key_times = np.array([k.time for k in script.hand])
    rows = []
    for f, t in enumerate(times):
        i, j, s = bracket(key_times, t)
        head_rot = Rotation.from_rotvec(params["flame_global_orient"][f]) * Rotation.from_rotvec(
            params["flame_neck_pose"][f]
        )
        rows.append(placer.frame_params(script.hand[i], script.hand[j], s, faces[f], head_rot))
    hand_pose, orient, transl, curl = (np.stack(c) for c in zip(*rows))
    params.update(
        mano_shape=np.tile(identity.mano_shape, (times.shape[0], 1)),
        mano_hand_pose=hand_pose,
        mano_global_orient=orient,
        mano_transl=transl,
    )
    out = mano(*(_as_t(params[k]) for k in ("mano_shape", "mano_hand_pose", "mano_global_orient", "mano_transl")))
    return Performance(
        params=params,
        face_vertices=faces,
        hand_vertices=out.vertices.numpy(),
        hand_joints=out.joints.numpy(),
        curl=curl,
    )
