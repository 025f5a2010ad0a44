"""Per-frame inputs of the dynamic model: poses, expression, the hand-to-head transform, PBD offsets.

Conventions (the paper names the inputs, not their encoding; these are ours):

- rotations enter the MLPs as the first two columns of the rotation matrix (the continuous 6-D
  representation of Zhou et al. 2019), not as axis-angle, which jumps at pi;
- the head frame is FLAME's root joint: origin at the posed root joint, axes rotated by
  ``flame_global_orient``; ``r_rel = R_head^T R_hand`` and ``t_rel = R_head^T (wrist - head_root)``,
  the wrist being MANO's root joint, in decimetres (so a hand at the cheek is of unit size);
- ``theta_face`` is FLAME's neck, jaw and eye pose (12 values; the global orientation is in r_rel);
- the PBD offsets ``d`` are rotated into the head frame (metres), so they do not change when the
  whole head turns.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import TypeAlias

import numpy as np
import torch
from torch import Tensor

from avatar.device import to_device
from avatar.posing import pose_layers
from avatar.templates import TemplateModel
from avatar.templates.lbs import batch_rodrigues

TRANSLATION_UNIT_M = 0.1  # t_rel in decimetres


def rotation_6d(R: Tensor) -> Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns, column-major."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


@dataclass
class Conditioning:
    """The dynamic model's inputs, float32: one frame, or a sequence with a leading T axis on every field
    (then :meth:`frame` takes one out).

    Attributes (one frame):
        hand_pose: (45,) theta_hand, MANO finger pose, axis-angle radians.
        hand_rotation: (6,) r_hand, the hand's global rotation (6-D).
        face_pose: (12,) theta_face: FLAME neck, jaw, eyes (axis-angle radians).
        expression: (E,) psi.
        rel_rotation: (6,) r_rel, hand rotation in the head frame (6-D).
        rel_translation: (3,) t_rel, wrist in the head frame (decimetres).
        head_rotation: (3, 3) head frame axes in world coordinates (columns).
        head_origin: (3,) head frame origin in the world (metres).
        face_offsets: (V_face, 3) PBD offsets of the face vertices in the head frame (metres).
    """

    hand_pose: Tensor
    hand_rotation: Tensor
    face_pose: Tensor
    expression: Tensor
    rel_rotation: Tensor
    rel_translation: Tensor
    head_rotation: Tensor
    head_origin: Tensor
    face_offsets: Tensor

    @property
    def num_frames(self) -> int:
        """T of a sequence."""
        return self.hand_pose.shape[0]

    def to(self, device: torch.device | str) -> Conditioning:
        """The same conditioning on ``device``."""
        return to_device(self, device)

    def frame(self, t: int) -> Conditioning:
        """Frame ``t`` of a sequence."""
        return Conditioning(**{f.name: getattr(self, f.name)[t] for f in fields(self)})

    def as_sequence(self) -> Conditioning:
        """One frame as a sequence of one frame (a leading axis of 1 on every field)."""
        return Conditioning(**{f.name: getattr(self, f.name)[None] for f in fields(self)})

    def to_head(self, points: Tensor) -> Tensor:
        """World points (N, 3) -> the head frame (N, 3), metres (one frame)."""
        return (points - self.head_origin) @ self.head_rotation


#: Names that say which of the two a signature expects.
FrameConditioning: TypeAlias = Conditioning
SequenceConditioning: TypeAlias = Conditioning


def sequence_conditioning(
    params: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel, face_offsets: Tensor | None = None
) -> SequenceConditioning:
    """The conditioning of every frame of ``params`` (the columns of ``params.parquet``).

    Args:
        params: flame_* and mano_* arrays with T rows.
        head, hand: the templates the parameters belong to.
        face_offsets: (T, V_face, 3) world-frame PBD offsets added to the posed face (the pbd stage's
            ``deform.parquet``), or None for none.
    """
    _, face, _, hand_out = pose_layers(params, head, hand, torch.float32)
    t = {name: torch.tensor(np.array(params[name]), dtype=torch.float32) for name in params}
    if face_offsets is None:
        face_offsets = torch.zeros_like(face.vertices)
    return conditioning_from_posed(t, face.joints[:, 0], hand_out.joints[:, 0], face_offsets)


def conditioning_from_posed(
    t: Mapping[str, Tensor], head_origin: Tensor, wrist: Tensor, face_offsets: Tensor
) -> SequenceConditioning:
    """The conditioning of T posed frames.

    Args:
        t: the params.parquet columns as float32 tensors (T, D).
        head_origin: (T, 3) FLAME's posed root joint; wrist: (T, 3) MANO's posed root joint (metres).
        face_offsets: (T, V_face, 3) world-frame PBD offsets added to the posed face.
    """
    R_head = batch_rodrigues(t["flame_global_orient"])
    R_hand = batch_rodrigues(t["mano_global_orient"])
    T = R_head.shape[0]
    return SequenceConditioning(
        hand_pose=t["mano_hand_pose"],
        hand_rotation=rotation_6d(R_hand),
        face_pose=torch.cat([t["flame_neck_pose"], t["flame_jaw_pose"], t["flame_eye_pose"]], dim=1),
        expression=t["flame_expression"].reshape(T, -1),
        rel_rotation=rotation_6d(R_head.transpose(-1, -2) @ R_hand),
        rel_translation=((wrist - head_origin)[:, None, :] @ R_head)[:, 0] / TRANSLATION_UNIT_M,
        head_rotation=R_head,
        head_origin=head_origin,
        face_offsets=face_offsets.to(torch.float32) @ R_head,  # row vectors: d R = (R^T d^T)^T
    )
