"""Small meshes for the SplattingAvatar tests."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from avatar.templates import procedural_hand, procedural_head


def grid(n: int = 4, size: float = 0.4, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """An open (n x n)-vertex square in the z = 0 plane, centred at the origin: (V, 3), (2 (n-1)^2, 3)."""
    t = torch.linspace(-size / 2, size / 2, n, dtype=dtype)
    y, x = torch.meshgrid(t, t, indexing="ij")
    verts = torch.stack([x.flatten(), y.flatten(), torch.zeros(n * n, dtype=dtype)], -1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            faces += [[a, b, e], [a, e, d]]
    return verts, torch.tensor(faces)


def bumpy(verts: Tensor) -> Tensor:
    """The grid with a smooth bump (a curved open surface)."""
    out = verts.clone()
    out[:, 2] = 0.1 * torch.cos(4 * out[:, 0]) * torch.sin(5 * out[:, 1] + 0.3)
    return out


def template(name: str, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """The procedural hand or head: vertices (V, 3), faces (F, 3)."""
    model = procedural_hand() if name == "hand" else procedural_head()
    return torch.tensor(model.v_template, dtype=dtype), torch.tensor(model.faces, dtype=torch.long)


def deform(verts: Tensor) -> Tensor:
    """A smooth non-rigid deformation (bend, twist, stretch) followed by a rotation and a shift."""
    centre = verts.mean(0)
    p = verts - centre
    angle = 3.0 * p[:, 1]
    c, s = torch.cos(angle), torch.sin(angle)
    twisted = torch.stack(
        [c * p[:, 0] - s * p[:, 2], 1.3 * p[:, 1] + 0.5 * p[:, 0] ** 2, s * p[:, 0] + c * p[:, 2]], -1
    )
    return twisted @ rotation_z(0.7).to(verts.dtype).T + verts.new_tensor([0.1, -0.2, 0.3])


def rotation_z(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def with_holes(verts: Tensor, faces: Tensor, every: int = 7) -> tuple[Tensor, Tensor]:
    """The mesh with every ``every``-th face removed (boundary edges all over it)."""
    keep = torch.arange(faces.shape[0]) % every != 0
    return verts, faces[keep]


def hand_and_head(dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    """Both templates as two parts of one mesh, the head with holes: vertices (V, 3), faces (F, 3),
    face_part (F,) (0 hand, 1 head)."""
    hand_v, hand_f = template("hand", dtype)
    head_v, head_f = with_holes(*template("head", dtype))
    faces = torch.cat([hand_f, head_f + hand_v.shape[0]])
    face_part = torch.cat([torch.zeros(len(hand_f)), torch.ones(len(head_f))]).long()
    return torch.cat([hand_v, head_v + 0.3]), faces, face_part
