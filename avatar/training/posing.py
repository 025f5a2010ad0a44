"""Posed FLAME + MANO meshes of every frame, from per-frame parameters."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel
from avatar.training.data import MeshSequence, concat_meshes


def posed_meshes(params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel,
                 face_offsets: np.ndarray | None = None) -> MeshSequence:
    """Face and hand meshes for the T frames of ``params`` (the columns of ``params.parquet``).

    Args:
        params: flame_* and mano_* arrays with T rows (radians, metres).
        head, hand: the FLAME and MANO templates the parameters belong to.
        face_offsets: optional (T, V_face, 3) per-vertex displacement added to the posed face
            (contact deformation from PBD or ground truth).
    Returns:
        A :class:`MeshSequence` with parts ("face", "hand"), float32.
    """
    t = {k: torch.tensor(np.asarray(v), dtype=torch.float32) for k, v in params.items()}
    flame = FLAMELayer(head, num_shape=t["flame_shape"].shape[1], num_expression=t["flame_expression"].shape[1])
    mano = MANOLayer(hand)
    with torch.no_grad():
        face = flame(t["flame_shape"], t["flame_expression"], t["flame_global_orient"], t["flame_neck_pose"],
                     t["flame_jaw_pose"], t["flame_eye_pose"], t["flame_transl"]).vertices
        hand_v = mano(t["mano_shape"], t["mano_hand_pose"], t["mano_global_orient"], t["mano_transl"]).vertices
    if face_offsets is not None:
        face = face + torch.as_tensor(face_offsets, dtype=face.dtype)
    return concat_meshes({
        "face": (face, torch.tensor(head.faces, dtype=torch.long)),
        "hand": (hand_v, torch.tensor(hand.faces, dtype=torch.long)),
    })


def posed_keypoints(params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel
                    ) -> dict[str, np.ndarray]:
    """3D keypoints of every frame: ``hand`` (T, 21, 3) in OpenPose order and ``face`` (T, L, 3)
    landmarks, plus the posed ``hand_vertices`` and ``face_vertices`` (float64, metres)."""
    t = {k: torch.tensor(np.asarray(v), dtype=torch.float64) for k, v in params.items()}
    flame = FLAMELayer(head, num_shape=t["flame_shape"].shape[1], num_expression=t["flame_expression"].shape[1])
    mano = MANOLayer(hand)
    with torch.no_grad():
        face = flame(t["flame_shape"], t["flame_expression"], t["flame_global_orient"], t["flame_neck_pose"],
                     t["flame_jaw_pose"], t["flame_eye_pose"], t["flame_transl"])
        hand_out = mano(t["mano_shape"], t["mano_hand_pose"], t["mano_global_orient"], t["mano_transl"])
        return {"hand": mano.keypoints21(hand_out.vertices, hand_out.joints).numpy(),
                "face": flame.landmarks(face.vertices).numpy(),
                "hand_vertices": hand_out.vertices.numpy(), "face_vertices": face.vertices.numpy()}
