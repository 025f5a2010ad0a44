"""Per-sequence MANO and FLAME parameter sets as ``torch.nn.Module``s.

Shape is one row shared by all frames; every other parameter has one row per
frame. All parameters are float64. ``forward`` returns world vertices and
keypoints of every frame; ``columns`` exports the parameter table in the
project's column layout (see :class:`avatar.synthetic.SyntheticCapture`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel

DTYPE = torch.float64


class Posed(NamedTuple):
    """vertices (T, V, 3) and keypoints (T, K, 3), world metres."""

    vertices: torch.Tensor
    keypoints: torch.Tensor


def _param(rows: int, width: int, init: np.ndarray | None = None) -> torch.nn.Parameter:
    value = torch.zeros(rows, width, dtype=DTYPE) if init is None else torch.as_tensor(init, dtype=DTYPE).clone()
    return torch.nn.Parameter(value)


class HandParams(torch.nn.Module):
    """MANO over T frames: shape (1, 10), hand_pose (T, 45), global_orient (T, 3), transl (T, 3)."""

    def __init__(self, model: TemplateModel, num_frames: int) -> None:
        super().__init__()
        self.layer = MANOLayer(model)
        self.num_frames = num_frames
        self.shape = _param(1, self.layer.num_betas)
        self.hand_pose = _param(num_frames, self.layer.pose_dim)
        self.global_orient = _param(num_frames, 3)
        self.transl = _param(num_frames, 3)

    def rest(self) -> tuple[np.ndarray, np.ndarray]:
        """Rest-pose keypoints (21, 3) and root joint (3,) of the current shape."""
        with torch.no_grad():
            out = self.layer(self.shape, torch.zeros(1, self.layer.pose_dim, dtype=DTYPE))
            return self.layer.keypoints21(out.vertices, out.joints)[0].numpy(), out.joints[0, 0].numpy()

    def forward(self) -> Posed:
        out = self.layer(self.shape.expand(self.num_frames, -1), self.hand_pose, self.global_orient, self.transl)
        return Posed(out.vertices, self.layer.keypoints21(out.vertices, out.joints))

    def pose_terms(self) -> list[torch.Tensor]:
        """Per-frame articulation parameters for the pose prior, (T, D) each."""
        return [self.hand_pose]

    def motion_terms(self) -> list[torch.Tensor]:
        """Per-frame rotations and articulation (T, D) each, smoothed over time."""
        return [self.global_orient, *self.pose_terms()]

    def columns(self) -> dict[str, np.ndarray]:
        T = self.num_frames
        return {
            "mano_shape": self.shape.detach().expand(T, -1).numpy().copy(),
            "mano_hand_pose": self.hand_pose.detach().numpy().copy(),
            "mano_global_orient": self.global_orient.detach().numpy().copy(),
            "mano_transl": self.transl.detach().numpy().copy(),
        }


class FaceParams(torch.nn.Module):
    """FLAME over T frames: shape (1, S), expression (T, E), global_orient / neck_pose /
    jaw_pose (T, 3), transl (T, 3); eye_pose stays zero (landmarks do not see the eyeballs)."""

    def __init__(self, model: TemplateModel, num_frames: int) -> None:
        super().__init__()
        num_shape = int(model.num_shape)
        self.layer = FLAMELayer(model, num_shape, model.num_shapes_total - num_shape)
        self.num_frames = num_frames
        self.shape = _param(1, num_shape)
        self.expression = _param(num_frames, self.layer.num_expression)
        self.global_orient = _param(num_frames, 3)
        self.neck_pose = _param(num_frames, 3)
        self.jaw_pose = _param(num_frames, 3)
        self.transl = _param(num_frames, 3)
        self.register_buffer("eye_pose", torch.zeros(num_frames, 6, dtype=DTYPE))

    @property
    def faces(self) -> torch.Tensor:
        return self.layer.faces

    def rest(self) -> tuple[np.ndarray, np.ndarray]:
        """Rest-pose landmarks (68, 3) and root joint (3,) of the current shape."""
        with torch.no_grad():
            out = self.layer(self.shape, torch.zeros(1, self.layer.num_expression, dtype=DTYPE))
            return self.layer.landmarks(out.vertices)[0].numpy(), out.joints[0, 0].numpy()

    def forward(self) -> Posed:
        out = self.layer(self.shape.expand(self.num_frames, -1), self.expression, self.global_orient,
                         self.neck_pose, self.jaw_pose, self.eye_pose, self.transl)
        return Posed(out.vertices, self.layer.landmarks(out.vertices))

    def pose_terms(self) -> list[torch.Tensor]:
        return [self.expression, self.jaw_pose, self.neck_pose]

    def motion_terms(self) -> list[torch.Tensor]:
        return [self.global_orient, *self.pose_terms()]

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
