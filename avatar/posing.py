"""Posed FLAME + MANO meshes of every frame, from per-frame parameters, and the mesh sequence they make.

Below both the training loops (:mod:`avatar.training`) and the dynamic model (:mod:`avatar.dynamic`), which
pose the templates alike; it imports only the templates (and the device move).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from avatar.device import to_device
from avatar.templates import FLAMELayer, LayerOutput, MANOLayer, TemplateModel


@dataclass
class MeshSequence:
    """The posed meshes of every frame, face and hand concatenated.

    Attributes:
        vertices: (T, V, 3) world positions.
        faces: (F, 3) int64.
        face_part: (F,) int64 index into ``part_names``.
        part_names: e.g. ("face", "hand").
    """

    vertices: Tensor
    faces: Tensor
    face_part: Tensor
    part_names: tuple[str, ...]

    def to(self, device: torch.device | str) -> MeshSequence:
        """The same meshes on ``device``."""
        return to_device(self, device)

    def extent(self) -> float:
        """Radius of the bounding sphere of all frames' vertices (the 3DGS 'scene extent')."""
        flat = self.vertices.reshape(-1, 3)
        centre = flat.mean(0)
        return float((flat - centre).norm(dim=-1).max())


def concat_meshes(parts: dict[str, tuple[Tensor, Tensor]]) -> MeshSequence:
    """Join named meshes ``name -> (vertices (T, V_i, 3), faces (F_i, 3))`` into one sequence."""
    verts, faces, face_part = [], [], []
    offset = 0
    for index, (v, f) in enumerate(parts.values()):
        verts.append(v)
        faces.append(f + offset)
        face_part.append(torch.full((f.shape[0],), index, dtype=torch.long))
        offset += v.shape[1]
    return MeshSequence(torch.cat(verts, dim=1), torch.cat(faces), torch.cat(face_part), tuple(parts))


def template_layers(
    params: Mapping[str, np.ndarray | torch.Tensor], head: TemplateModel, hand: TemplateModel
) -> tuple[FLAMELayer, MANOLayer]:
    """The FLAME and MANO layers for parameters (arrays or tensors) as wide as ``params`` holds."""
    return FLAMELayer.for_params(head, params), MANOLayer(hand)


def run_layers(flame: FLAMELayer, mano: MANOLayer, t: Mapping[str, torch.Tensor]) -> tuple[LayerOutput, LayerOutput]:
    """(face, hand) layer outputs of the B frames of ``t`` (the params.parquet columns as (B, D) tensors);
    differentiable in every column."""
    face = flame(
        t["flame_shape"],
        t["flame_expression"],
        t["flame_global_orient"],
        t["flame_neck_pose"],
        t["flame_jaw_pose"],
        t["flame_eye_pose"],
        t["flame_transl"],
    )
    return face, mano(t["mano_shape"], t["mano_hand_pose"], t["mano_global_orient"], t["mano_transl"])


def pose_layers(
    params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel, dtype: torch.dtype
) -> tuple[FLAMELayer, LayerOutput, MANOLayer, LayerOutput]:
    """Run the FLAME and MANO layers on every frame of ``params`` (no gradients)."""
    t = {k: torch.tensor(np.asarray(v), dtype=dtype) for k, v in params.items()}
    flame, mano = template_layers(t, head, hand)
    with torch.no_grad():
        face, hand_out = run_layers(flame, mano, t)
    return flame, face, mano, hand_out


def posed_meshes(params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel) -> MeshSequence:
    """Face and hand meshes for the T frames of ``params`` (the columns of ``params.parquet``).

    Args:
        params: flame_* and mano_* arrays with T rows (radians, metres).
        head, hand: the FLAME and MANO templates the parameters belong to.
    Returns:
        A :class:`MeshSequence` with parts ("face", "hand"), float32.
    """
    _, face, _, hand_out = pose_layers(params, head, hand, torch.float32)
    return concat_meshes(
        {
            "face": (face.vertices, torch.tensor(head.faces, dtype=torch.long)),
            "hand": (hand_out.vertices, torch.tensor(hand.faces, dtype=torch.long)),
        }
    )


def posed_keypoints(
    params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel
) -> dict[str, np.ndarray]:
    """3D keypoints of every frame: ``hand`` (T, 21, 3) in OpenPose order and ``face`` (T, L, 3)
    landmarks, plus the posed ``hand_vertices`` and ``face_vertices`` (float64, metres)."""
    flame, face, mano, hand_out = pose_layers(params, head, hand, torch.float64)
    with torch.no_grad():
        return {
            "hand": mano.keypoints21(hand_out.vertices, hand_out.joints).numpy(),
            "face": flame.landmarks(face.vertices).numpy(),
            "hand_vertices": hand_out.vertices.numpy(),
            "face_vertices": face.vertices.numpy(),
        }
