"""A viewer folder made in a second, without the DAG: a toy avatar of bound Gaussians on two bent grids (``face`` and a
smaller ``hand`` that moves in front of it), whose hand changes with the frame as H makes it change (a pose-dependent
offset and colour), written by the stage's own writer (:func:`avatar.viewer.page.write_viewer`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatar.artifacts import PosedGaussians
from avatar.artifacts.motion import PosedSequence
from avatar.posing import MeshSequence
from avatar.render.gaussians import render_gaussians
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.viewer.codec import CodecConfig
from avatar.viewer.page import Motion, PageSettings, write_viewer

SIZE = 96
BACKGROUND = [0.3, 0.35, 0.4]
K = [[200.0, 0.0, 47.0], [0.0, 200.0, 48.5], [0.0, 0.0, 1.0]]
#: two cameras in front of the grids (OpenCV: x right, y down, z forward), the second turned about the vertical
CAMERAS = {
    "front": np.array([[1.0, 0, 0, 0], [0, -1, 0, 0.0], [0, 0, -1, 0.45], [0, 0, 0, 1]]),
    "side": np.array(
        [[np.cos(0.4), 0, -np.sin(0.4), 0], [0, -1, 0, 0.0], [-np.sin(0.4), 0, -np.cos(0.4), 0.45], [0, 0, 0, 1]]
    ),
}


def _grid(n: int, size: float, bend: float) -> tuple[np.ndarray, np.ndarray]:
    """A bent square grid in the z = 0 plane, n x n vertices: (V, 3), faces (F, 3)."""
    u, v = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n))
    vertices = np.stack([u, v, -bend * (u**2 + v**2)], -1).reshape(-1, 3)
    faces = [[r * n + c, r * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)]
    faces += [[r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)]
    return vertices, np.asarray(faces)


def toy_meshes(frames: int) -> tuple[MeshSequence, np.ndarray]:
    """Face (a 12 x 12 grid, 16 cm) and hand (6 x 6, 6 cm, moving across and towards it): the sequence and the
    rest vertices (V, 3)."""
    face_v, face_f = _grid(12, 0.16, 1.5)
    hand_v, hand_f = _grid(6, 0.06, 0.0)
    rest = np.concatenate([face_v, hand_v + [0, 0, 0.03]])
    sequence = []
    for t in range(frames):
        shift = np.array([-0.04 + 0.08 * t / max(frames - 1, 1), 0.01 * np.sin(t), 0.03 - 0.02 * t / max(frames, 1)])
        sequence.append(np.concatenate([face_v, hand_v + shift]))
    faces = np.concatenate([face_f, hand_f + len(face_v)])
    part = np.concatenate([np.zeros(len(face_f)), np.ones(len(hand_f))]).astype(np.int64)
    meshes = MeshSequence(torch.tensor(np.stack(sequence)), torch.tensor(faces), torch.tensor(part), ("face", "hand"))
    return meshes, rest


class NoConditioning:
    """The conditioning of a motion whose avatar reads none (the toy's): it moves to any device as itself."""

    def to(self, device: object) -> NoConditioning:
        return self


@dataclass
class ToyAvatar:
    """Bound Gaussians whose hand ones move up to 2 mm and brighten with the frame (what H does to a real hand)."""

    gaussians: BoundGaussians
    faces: torch.Tensor
    hand: torch.Tensor

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    @property
    def triangles(self) -> torch.Tensor:
        return self.gaussians.binding

    def on_device(self, device: str, precision: str) -> ToyAvatar:
        return self  # the tests' toy runs on the CPU

    def pose(self, cond: object, vertices: torch.Tensor, frame: int) -> PosedGaussians:
        means, scales, quats = self.gaussians.world(vertices, self.faces)
        colors = self.gaussians.colors().clone()
        means = means + self.hand[:, None] * torch.tensor([0.002 * np.sin(frame), 0.0, 0.0])
        colors[self.hand] = (colors[self.hand] + 0.05 * frame).clamp(0, 1)
        return PosedGaussians(means, scales, quats, self.gaussians.opacities(), colors)


def toy_avatar(meshes: MeshSequence, rest: np.ndarray) -> ToyAvatar:
    gaussians = BoundGaussians.on_triangles(
        torch.tensor(rest), meshes.faces, meshes.face_part, 2, init_opacity=0.9, seed=0
    )
    with torch.no_grad():
        rng = np.random.default_rng(0)
        face = gaussians.part == 0
        base = np.where(face.numpy()[:, None], [0.8, 0.6, 0.5], [0.9, 0.75, 0.6])
        colors = base + rng.uniform(-0.1, 0.1, (len(face), 3))
        gaussians.set_colors(torch.tensor(colors).clamp(0, 1))
    return ToyAvatar(gaussians, meshes.faces, gaussians.part == 1)


def render(avatar: ToyAvatar, meshes: MeshSequence, frame: int, camera: str) -> np.ndarray:
    """The project's render of the toy's frame at one of :data:`CAMERAS`, (SIZE, SIZE, 3) float32."""
    with torch.no_grad():
        g = avatar.pose(None, meshes.vertices[frame], frame)
        out = render_gaussians(
            g.means.float(),
            g.quats.float(),
            g.scales.float(),
            g.opacities.float(),
            g.colors.float(),
            torch.tensor(K),
            torch.tensor(CAMERAS[camera], dtype=torch.float32),
            SIZE,
            SIZE,
            torch.tensor(BACKGROUND),
        )
    return out.rgb.clamp(0, 1).numpy()


def write_toy_viewer(out_dir: Path, frames: int = 8) -> tuple[ToyAvatar, dict[str, MeshSequence]]:
    """Write the toy's viewer into ``out_dir`` (two motions, ``train`` and ``test``, the first with ground truth: the
    project's own renders); returns the avatar and each motion's meshes."""
    meshes, rest = toy_meshes(frames)
    avatar = toy_avatar(meshes, rest)
    reverse = MeshSequence(meshes.vertices.flip(0), meshes.faces, meshes.face_part, meshes.part_names)
    sequences = {"train": meshes, "test": reverse}
    cameras = [
        {"id": name, "K": K, "world_to_cam": w2c.tolist(), "width": SIZE, "height": SIZE}
        for name, w2c in CAMERAS.items()
    ]
    truth = np.stack([np.stack([render(avatar, meshes, t, c) for c in CAMERAS]) for t in range(frames)])
    motions = [
        Motion(
            name,
            f"toy {name}",
            PosedSequence({}, seq, np.zeros((frames, 144, 3))),
            NoConditioning(),  # type: ignore[arg-type]  # the toy's pose reads none
            np.arange(frames) % 3 == 1,
            cameras,
            (truth * 255).round().astype(np.uint8) if name == "train" else None,
            BACKGROUND,
        )
        for name, seq in sequences.items()
    ]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_viewer(out_dir, avatar, motions, CodecConfig(), PageSettings(), {"method": "toy", "label": "toy"})
    return avatar, sequences
