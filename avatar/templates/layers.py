"""MANO and FLAME as ``torch.nn.Module`` layers over a :class:`TemplateModel`.

Buffers are stored in float64; ``forward`` casts them to the dtype and device
of its inputs, so the same layer serves float32 training and float64 checks.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
import torch

from avatar.templates.lbs import lbs
from avatar.templates.model import TemplateModel

# OpenPose hand order (wrist, thumb1-4, index1-4, middle1-4, ring1-4, pinky1-4)
# as indices into [16 MANO joints, 5 tips (thumb, index, middle, ring, pinky)].
OPENPOSE_FROM_MANO = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
MANO_NUM_JOINTS = 16


def hand_frame(joints: np.ndarray) -> np.ndarray:
    """(3, 3) anatomical frame of a hand from its joints (16, 3) in MANO order (0 wrist, 1 index, 4 middle and
    7 little finger knuckles): columns wrist-to-middle-knuckle (``finger``), palm normal (``palm``) and
    ``finger x palm`` (``lateral``)."""
    finger = joints[4] - joints[0]
    finger = finger / np.linalg.norm(finger, axis=-1, keepdims=True)
    palm = np.cross(joints[1] - joints[7], finger)
    palm = palm / np.linalg.norm(palm, axis=-1, keepdims=True)
    return np.stack([finger, palm, np.cross(finger, palm)], axis=1)


FLAME_NUM_JOINTS = 5


class LayerOutput(NamedTuple):
    """vertices (B, V, 3) and joints (B, J, 3), both in world space (translation applied)."""

    vertices: torch.Tensor
    joints: torch.Tensor


class _SkinnedLayer(torch.nn.Module):
    """Registers a template's arrays as float64 buffers and runs LBS on them."""

    v_template: torch.Tensor
    shapedirs: torch.Tensor
    posedirs: torch.Tensor
    J_regressor: torch.Tensor
    weights: torch.Tensor
    faces: torch.Tensor

    def __init__(self, model: TemplateModel, shape_columns: np.ndarray) -> None:
        super().__init__()
        self.model = model
        self.parents: list[int] = [int(p) for p in model.parents]
        self.register_buffer("v_template", torch.from_numpy(np.array(model.v_template)))
        self.register_buffer("shapedirs", torch.from_numpy(np.array(model.shapedirs[:, :, shape_columns])))
        self.register_buffer("posedirs", torch.from_numpy(np.array(model.posedirs)))
        self.register_buffer("J_regressor", torch.from_numpy(np.array(model.J_regressor)))
        self.register_buffer("weights", torch.from_numpy(np.array(model.weights)))
        self.register_buffer("faces", torch.from_numpy(np.array(model.faces)))

    def _skin(self, betas: torch.Tensor, pose: torch.Tensor, transl: torch.Tensor) -> LayerOutput:
        """betas (B, S), pose (B, J, 3) axis-angle, transl (B, 3) -> LayerOutput."""
        dtype, device = betas.dtype, betas.device
        vertices, joints = lbs(
            betas,
            pose,
            self.v_template.to(dtype=dtype, device=device),
            self.shapedirs.to(dtype=dtype, device=device),
            self.posedirs.to(dtype=dtype, device=device),
            self.J_regressor.to(dtype=dtype, device=device),
            self.parents,
            self.weights.to(dtype=dtype, device=device),
        )
        offset = transl[:, None, :]
        return LayerOutput(vertices + offset, joints + offset)


def _check(name: str, value: torch.Tensor, batch: int, width: int) -> None:
    if value.ndim != 2 or value.shape != (batch, width):
        raise ValueError(f"{name} must have shape ({batch}, {width}), got {tuple(value.shape)}")
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {value.dtype}")


def _zeros_if_none(value: torch.Tensor | None, like: torch.Tensor, width: int) -> torch.Tensor:
    return like.new_zeros(like.shape[0], width) if value is None else value


class MANOLayer(_SkinnedLayer):
    """MANO hand: 16 joints (0 wrist, 1-3 index, 4-6 middle, 7-9 pinky, 10-12 ring, 13-15 thumb)."""

    hands_components: torch.Tensor
    hands_mean: torch.Tensor
    tip_vertex_ids: torch.Tensor

    def __init__(
        self,
        model: TemplateModel,
        use_pca: bool = False,
        num_pca_comps: int = 45,
        flat_hand_mean: bool = True,
    ) -> None:
        if model.name != "mano" or model.num_joints != MANO_NUM_JOINTS:
            raise ValueError(
                f"MANOLayer needs a 16-joint 'mano' TemplateModel, got {model.name!r} with {model.num_joints} joints"
            )
        if model.hands_components is None or model.hands_mean is None or model.tip_vertex_ids is None:
            raise ValueError("MANOLayer needs hands_components, hands_mean and tip_vertex_ids in the model")
        if use_pca and not 1 <= num_pca_comps <= model.hands_components.shape[0]:
            raise ValueError(f"num_pca_comps must lie in [1, {model.hands_components.shape[0]}], got {num_pca_comps}")
        super().__init__(model, np.arange(model.num_shapes_total))
        self.use_pca = use_pca
        self.num_pca_comps = num_pca_comps
        self.flat_hand_mean = flat_hand_mean
        self.num_betas = model.num_shapes_total
        self.register_buffer("hands_components", torch.from_numpy(np.array(model.hands_components[:num_pca_comps])))
        self.register_buffer("hands_mean", torch.from_numpy(np.array(model.hands_mean)))
        self.register_buffer("tip_vertex_ids", torch.from_numpy(np.array(model.tip_vertex_ids)))

    @property
    def pose_dim(self) -> int:
        """Width of ``hand_pose``: ``num_pca_comps`` with PCA, else 45."""
        return self.num_pca_comps if self.use_pca else 3 * (MANO_NUM_JOINTS - 1)

    def full_hand_pose(self, hand_pose: torch.Tensor) -> torch.Tensor:
        """(B, pose_dim) -> (B, 45) axis-angle of joints 1..15 (PCA and mean applied)."""
        dtype, device = hand_pose.dtype, hand_pose.device
        full = hand_pose @ self.hands_components.to(dtype=dtype, device=device) if self.use_pca else hand_pose
        return full if self.flat_hand_mean else full + self.hands_mean.to(dtype=dtype, device=device)

    def forward(
        self,
        betas: torch.Tensor,
        hand_pose: torch.Tensor,
        global_orient: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
    ) -> LayerOutput:
        """betas (B, S), hand_pose (B, pose_dim), global_orient (B, 3), transl (B, 3)
        -> vertices (B, V, 3), joints (B, 16, 3)."""
        batch = betas.shape[0]
        global_orient = _zeros_if_none(global_orient, betas, 3)
        transl = _zeros_if_none(transl, betas, 3)
        _check("betas", betas, batch, self.num_betas)
        _check("hand_pose", hand_pose, batch, self.pose_dim)
        _check("global_orient", global_orient, batch, 3)
        _check("transl", transl, batch, 3)
        pose = torch.cat((global_orient, self.full_hand_pose(hand_pose)), dim=1).reshape(batch, MANO_NUM_JOINTS, 3)
        return self._skin(betas, pose, transl)

    def keypoints21(self, vertices: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """vertices (B, V, 3), joints (B, 16, 3) -> (B, 21, 3) keypoints in OpenPose order."""
        tips = vertices[:, self.tip_vertex_ids]
        return torch.cat((joints, tips), dim=1)[:, list(OPENPOSE_FROM_MANO)]


class FLAMELayer(_SkinnedLayer):
    """FLAME head: 5 joints (0 global, 1 neck, 2 jaw, 3 left eye, 4 right eye)."""

    landmark_faces: torch.Tensor
    landmark_bary: torch.Tensor

    def __init__(self, model: TemplateModel, num_shape: int, num_expression: int) -> None:
        if model.name != "flame" or model.num_joints != FLAME_NUM_JOINTS:
            raise ValueError(
                f"FLAMELayer needs a 5-joint 'flame' TemplateModel, got {model.name!r} with {model.num_joints} joints"
            )
        num_expr_total = model.num_shapes_total - model.num_identity_shape
        if not 0 <= num_shape <= model.num_identity_shape:
            raise ValueError(f"num_shape must lie in [0, {model.num_shape}], got {num_shape}")
        if not 0 <= num_expression <= num_expr_total:
            raise ValueError(f"num_expression must lie in [0, {num_expr_total}], got {num_expression}")
        columns = np.concatenate((np.arange(num_shape), model.num_identity_shape + np.arange(num_expression))).astype(
            np.int64
        )
        super().__init__(model, columns)
        self.num_shape = num_shape
        self.num_expression = num_expression
        has_lmk = model.landmark_faces is not None
        lmk_faces = model.landmark_faces if has_lmk else np.zeros(0, dtype=np.int64)
        lmk_bary = model.landmark_bary if has_lmk else np.zeros((0, 3))
        self.has_landmarks = has_lmk
        self.register_buffer("landmark_faces", torch.from_numpy(np.array(lmk_faces)))
        self.register_buffer("landmark_bary", torch.from_numpy(np.array(lmk_bary)))

    @classmethod
    def for_params(cls, model: TemplateModel, params: Mapping[str, Any]) -> FLAMELayer:
        """The layer for parameters as wide as ``params`` holds: ``flame_shape`` (T, S') and
        ``flame_expression`` (T, E') use the first S' identity and E' expression columns (a
        synthetic subject's shape lies in the procedural head's first, designed columns)."""
        return cls(model, int(np.shape(params["flame_shape"])[1]), int(np.shape(params["flame_expression"])[1]))

    def forward(
        self,
        shape: torch.Tensor,
        expression: torch.Tensor,
        global_orient: torch.Tensor | None = None,
        neck_pose: torch.Tensor | None = None,
        jaw_pose: torch.Tensor | None = None,
        eye_pose: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
    ) -> LayerOutput:
        """shape (B, num_shape), expression (B, num_expression), global_orient / neck_pose /
        jaw_pose (B, 3), eye_pose (B, 6) = [left eye, right eye], transl (B, 3)
        -> vertices (B, V, 3), joints (B, 5, 3)."""
        batch = shape.shape[0]
        global_orient = _zeros_if_none(global_orient, shape, 3)
        neck_pose = _zeros_if_none(neck_pose, shape, 3)
        jaw_pose = _zeros_if_none(jaw_pose, shape, 3)
        eye_pose = _zeros_if_none(eye_pose, shape, 6)
        transl = _zeros_if_none(transl, shape, 3)
        _check("shape", shape, batch, self.num_shape)
        _check("expression", expression, batch, self.num_expression)
        for name, value in (
            ("global_orient", global_orient),
            ("neck_pose", neck_pose),
            ("jaw_pose", jaw_pose),
            ("transl", transl),
        ):
            _check(name, value, batch, 3)
        _check("eye_pose", eye_pose, batch, 6)
        betas = torch.cat((shape, expression), dim=1)
        pose = torch.cat((global_orient, neck_pose, jaw_pose, eye_pose), dim=1).reshape(batch, FLAME_NUM_JOINTS, 3)
        return self._skin(betas, pose, transl)

    def landmarks(self, vertices: torch.Tensor) -> torch.Tensor:
        """vertices (B, V, 3) -> landmarks (B, L, 3) from the model's barycentric embedding."""
        if not self.has_landmarks:
            raise ValueError(
                "this FLAME model has no landmark embedding: pass landmark_embedding=... "
                "(flame_static_embedding.pkl) to load_official_model"
            )
        corners = vertices[:, self.faces[self.landmark_faces]]  # (B, L, 3, 3)
        bary = self.landmark_bary.to(dtype=vertices.dtype, device=vertices.device)
        return (corners * bary[None, :, :, None]).sum(dim=2)
