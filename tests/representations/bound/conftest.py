"""A tiny dynamic-model scene: the procedural head and hand, two frames (the hand at the cheek, the hand far
away), one 32 x 32 camera in front of the face, tiny MLPs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from avatar.dynamic import SequenceConditioning, sequence_conditioning
from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence, posed_meshes
from avatar.representations.bound.dynamic_model import DynamicAvatar, DynamicModelConfig
from avatar.representations.bound.gaussians import PARAM_NAMES, BoundGaussians
from avatar.templates import procedural_hand, procedural_head

SIZE = 32
GAUSSIAN_STRIDE = 6
NEAR, FAR = 0, 1  # frames: hand at the cheek, hand a metre away


def scene_params(hand_x: list[float]) -> dict[str, np.ndarray]:
    """Rest-pose head, slightly curled hand translated by ``hand_x`` metres along x in each frame."""
    T = len(hand_x)
    zeros = lambda w: np.zeros((T, w), np.float32)  # noqa: E731
    transl = zeros(3)
    transl[:, 0] = hand_x
    finger_curl = np.tile(np.linspace(-0.2, 0.3, 45, dtype=np.float32), (T, 1))
    return {
        "flame_shape": zeros(10),
        "flame_expression": zeros(10),
        "flame_global_orient": zeros(3),
        "flame_neck_pose": zeros(3),
        "flame_jaw_pose": zeros(3),
        "flame_eye_pose": zeros(6),
        "flame_transl": zeros(3),
        "mano_shape": zeros(10),
        "mano_hand_pose": finger_curl,
        "mano_global_orient": zeros(3),
        "mano_transl": transl,
    }


def front_view(num_frames: int, seed: int = 0) -> ViewSet:
    """One camera 0.6 m in front of the face (OpenCV axes), random images, labels with a hand on the right."""
    gen = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    w2c[2, 3] = 0.6
    labels = torch.ones(num_frames, 1, SIZE, SIZE, dtype=torch.uint8)
    labels[..., :, :4] = 0
    labels[..., 8:20, 20:30] = 2
    return ViewSet(
        images=torch.randint(0, 256, (num_frames, 1, SIZE, SIZE, 3), generator=gen, dtype=torch.uint8),
        labels=labels,
        K=torch.tensor([[[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]]]),
        world_to_cam=w2c[None],
        camera_ids=["front"],
        background=torch.zeros(3),
    )


TINY = DynamicModelConfig(
    hand_width=16,
    hand_depth=2,
    interaction_width=16,
    interaction_depth=3,
    position_frequencies=2,
    offset_frequencies=2,
    point_feature_dim=8,
    geometry_feature_dim=16,
    pointnet_centres=(16, 8),
    pointnet_width=0.125,
)


@dataclass
class Scene:
    meshes: MeshSequence
    cond: SequenceConditioning
    views: ViewSet
    num_face_vertices: int

    def model(self, cfg: DynamicModelConfig = TINY, seed: int = 0) -> DynamicAvatar:
        m = self.meshes
        full = BoundGaussians.on_triangles(m.vertices[0], m.faces, m.face_part, 1, init_opacity=0.5, seed=seed)
        keep = torch.arange(full.num_gaussians) % GAUSSIAN_STRIDE == 0  # a sixth of the triangles: fast tests
        g = BoundGaussians(
            *(getattr(full, n).detach()[keep] for n in PARAM_NAMES), binding=full.binding[keep], part=full.part[keep]
        )
        with torch.no_grad():
            g.sh_dc.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(seed))
        dims = {"hand_pose": self.cond.hand_pose.shape[1], "expression": self.cond.expression.shape[1]}
        return DynamicAvatar.from_warmup(
            g, m.vertices[0], m.faces, m.part_names, self.num_face_vertices, dims, cfg, seed=seed
        )


def make_scene(hand_x: list[float], dent_m: float = 0.004) -> Scene:
    head, hand = procedural_head(), procedural_hand()
    params = scene_params(hand_x)
    meshes = posed_meshes(params, head, hand)
    V = head.num_vertices
    offsets = torch.zeros(len(hand_x), V, 3)
    face = meshes.vertices[:, :V]
    cheek = face[..., 0] > face[..., 0].max() - 0.01  # the right cheek gives way by dent_m where the hand is
    offsets[..., 0] = torch.where(cheek & torch.tensor([x < 0.5 for x in hand_x])[:, None], -dent_m, 0.0)
    meshes.vertices[:, :V] += offsets
    return Scene(meshes, sequence_conditioning(params, head, hand, offsets), front_view(len(hand_x)), V)


@pytest.fixture(scope="session")
def scene() -> Scene:
    return make_scene([0.08, 1.0])
