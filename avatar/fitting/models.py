"""Per-sequence MANO and FLAME parameter sets as ``torch.nn.Module``s.

Shape is one row shared by all frames; every other parameter has one row per
frame. All parameters are float64. ``forward`` returns world vertices and
keypoints of every frame; ``columns`` exports the parameter table in the
project's column layout (see :class:`avatar.synthetic.SyntheticCapture`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
import torch

from avatar.fitting.hand_ik import hand_pose_ik
from avatar.fitting.rigid import fill_from_nearest, rigid_init
from avatar.templates import FLAMELayer, LayerOutput, MANOLayer, TemplateModel
from avatar.templates.reduce import keypoint_template

DTYPE = torch.float64
CM_PER_M = 100.0


class _PartParams(torch.nn.Module, ABC):
    """What both parts share: a per-frame global rotation, and a per-frame
    translation held in centimetres (a 1-unit step then moves a part about as far
    as a 1-unit step of a pose parameter, which keeps L-BFGS well conditioned;
    metres made translation steps ~100x too stiff)."""

    global_orient: torch.nn.Parameter
    transl_cm: torch.nn.Parameter

    @property
    def transl(self) -> torch.Tensor:
        """(T, 3) metres."""
        return self.transl_cm / CM_PER_M

    @abstractmethod
    def pose_terms(self) -> list[torch.Tensor]:
        """Per-frame articulation parameters for the pose prior, (T, D) each."""

    def motion_terms(self) -> list[torch.Tensor]:
        """Per-frame rotations and articulation (T, D) each, smoothed over time."""
        return [self.global_orient, *self.pose_terms()]


def _param(rows: int, width: int, init: np.ndarray | None = None) -> torch.nn.Parameter:
    value = torch.zeros(rows, width, dtype=DTYPE) if init is None else torch.as_tensor(init, dtype=DTYPE).clone()
    return torch.nn.Parameter(value)


class HandParams(_PartParams):
    """MANO over T frames: shape (1, 10), hand_pose (T, 45), global_orient (T, 3), transl (T, 3)."""

    def __init__(self, model: TemplateModel, num_frames: int) -> None:
        super().__init__()
        self.layer = MANOLayer(model)
        self.keypoint_layer = MANOLayer(keypoint_template(model))
        self.num_frames = num_frames
        self.shape = _param(1, self.layer.num_betas)
        self.hand_pose = _param(num_frames, self.layer.pose_dim)
        self.global_orient = _param(num_frames, 3)
        self.transl_cm = _param(num_frames, 3)  # centimetres: steps comparable to the rotations'

    def init_from_keypoints(self, points: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Set global_orient, transl and hand_pose by inverse kinematics on
        triangulated keypoints (T, 21, 3) with valid (T, 21) bool; frames
        without a palm copy their nearest frame that has one. Returns ok (T,)."""
        if self.layer.use_pca or not self.layer.flat_hand_mean:
            raise ValueError("inverse kinematics needs the full (non-PCA) flat-mean MANO pose")
        with torch.no_grad():
            out = self.layer(self.shape, torch.zeros(1, self.layer.pose_dim, dtype=DTYPE))
            joints, tips = out.joints[0].numpy(), out.vertices[0, self.layer.tip_vertex_ids].numpy()
        orient, transl, pose, ok = hand_pose_ik(joints, tips, self.layer.parents, points, valid)
        fill_from_nearest(ok, orient, transl, pose)
        with torch.no_grad():
            self.global_orient.copy_(torch.as_tensor(orient))
            self.transl_cm.copy_(torch.as_tensor(transl) * CM_PER_M)
            self.hand_pose.copy_(torch.as_tensor(pose))
        return ok

    def rest_keypoints(self) -> np.ndarray:
        """(21, 3) keypoints of the flat rest hand at the current shape, metres, OpenPose order."""
        with torch.no_grad():
            out = self.keypoint_layer(self.shape, torch.zeros(1, self.layer.pose_dim, dtype=DTYPE))
            return self.keypoint_layer.keypoints21(out.vertices, out.joints)[0].numpy()

    def _posed(self, layer: MANOLayer, frames: torch.Tensor | slice = slice(None)) -> LayerOutput:
        pose = self.hand_pose[frames]
        return layer(self.shape.expand(pose.shape[0], -1), pose, self.global_orient[frames], self.transl[frames])

    def keypoints(self) -> torch.Tensor:
        """(T, 21, 3) world keypoints in OpenPose order."""
        out = self._posed(self.keypoint_layer)
        return self.keypoint_layer.keypoints21(out.vertices, out.joints)

    def vertices(self, frames: torch.Tensor | slice = slice(None)) -> torch.Tensor:
        """(T', V, 3) world vertices of ``frames`` (int64 indices; default all T)."""
        return self._posed(self.layer, frames).vertices

    def pose_terms(self) -> list[torch.Tensor]:
        return [self.hand_pose]

    def columns(self) -> dict[str, np.ndarray]:
        T = self.num_frames
        return {
            "mano_shape": self.shape.detach().expand(T, -1).numpy().copy(),
            "mano_hand_pose": self.hand_pose.detach().numpy().copy(),
            "mano_global_orient": self.global_orient.detach().numpy().copy(),
            "mano_transl": self.transl.detach().numpy().copy(),
        }


class FaceParams(_PartParams):
    """FLAME over T frames: shape (1, S), expression (T, E), global_orient / neck_pose /
    jaw_pose (T, 3), transl (T, 3); eye_pose stays zero (landmarks do not see the eyeballs).
    ``shape_columns``: fit only the first S of the model's identity columns (None: all)."""

    eye_pose: torch.Tensor
    shape_roughness: torch.Tensor | None

    def __init__(self, model: TemplateModel, num_frames: int, shape_columns: int | None = None) -> None:
        super().__init__()
        num_shape = model.num_identity_shape if shape_columns is None else int(shape_columns)
        num_expression = model.num_shapes_total - model.num_identity_shape
        self.layer = FLAMELayer(model, num_shape, num_expression)
        self.keypoint_layer = FLAMELayer(keypoint_template(model), num_shape, num_expression)
        self.num_frames = num_frames
        self.shape = _param(1, num_shape)
        self.expression = _param(num_frames, self.layer.num_expression)
        self.global_orient = _param(num_frames, 3)
        self.neck_pose = _param(num_frames, 3)
        self.jaw_pose = _param(num_frames, 3)
        self.transl_cm = _param(num_frames, 3)  # centimetres: steps comparable to the rotations'
        self.register_buffer("eye_pose", torch.zeros(num_frames, 6, dtype=DTYPE))
        roughness = model.shape_roughness
        self.register_buffer(
            "shape_roughness",
            None if roughness is None else torch.tensor(roughness[:num_shape, :num_shape], dtype=DTYPE),
        )

    def roughness(self) -> torch.Tensor:
        """``beta^T R beta`` of the shared identity (0 for a template without ``shape_roughness``)."""
        if self.shape_roughness is None:
            return self.shape.new_zeros(())
        return (self.shape @ self.shape_roughness @ self.shape.T).sum()

    @property
    def faces(self) -> torch.Tensor:
        return self.layer.faces

    def rest_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """The rest pose's landmarks (68, 3) and root joint (3,), metres, at the current shape."""
        with torch.no_grad():
            out = self.layer(self.shape, torch.zeros(1, self.layer.num_expression, dtype=DTYPE))
            return self.layer.landmarks(out.vertices)[0].numpy(), out.joints[0, 0].numpy()

    def init_from_keypoints(self, points: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Set global_orient and transl by rigidly aligning the rest-pose landmarks
        to triangulated landmarks (T, 68, 3) with valid (T, 68) bool. Returns ok (T,)."""
        rest, root = self.rest_landmarks()
        orient, transl, ok = rigid_init(rest, root, points, valid)
        with torch.no_grad():
            self.global_orient.copy_(torch.as_tensor(orient))
            self.transl_cm.copy_(torch.as_tensor(transl) * CM_PER_M)
        return ok

    def _posed(self, layer: FLAMELayer, frames: torch.Tensor | slice = slice(None)) -> LayerOutput:
        expression = self.expression[frames]
        return layer(
            self.shape.expand(expression.shape[0], -1),
            expression,
            self.global_orient[frames],
            self.neck_pose[frames],
            self.jaw_pose[frames],
            self.eye_pose[frames],
            self.transl[frames],
        )

    def keypoints(self) -> torch.Tensor:
        """(T, 68, 3) world landmarks."""
        return self.keypoint_layer.landmarks(self._posed(self.keypoint_layer).vertices)

    def vertices(self, frames: torch.Tensor | slice = slice(None)) -> torch.Tensor:
        """(T', V, 3) world vertices of ``frames`` (int64 indices; default all T)."""
        return self._posed(self.layer, frames).vertices

    def pose_terms(self) -> list[torch.Tensor]:
        return [self.expression, self.jaw_pose, self.neck_pose]

    def columns(self) -> dict[str, np.ndarray]:
        T = self.num_frames
        return {
            "flame_shape": self.shape.detach().expand(T, -1).numpy().copy(),
            "flame_expression": self.expression.detach().numpy().copy(),
            "flame_global_orient": self.global_orient.detach().numpy().copy(),
            "flame_neck_pose": self.neck_pose.detach().numpy().copy(),
            "flame_jaw_pose": self.jaw_pose.detach().numpy().copy(),
            "flame_eye_pose": self.eye_pose.numpy().copy(),
            "flame_transl": self.transl.detach().numpy().copy(),
        }
