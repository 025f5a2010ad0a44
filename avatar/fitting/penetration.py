"""A cheap differentiable signed-distance proxy for hand-face interpenetration.

The proxy signed distance of a hand point is its offset from its nearest face
vertex along that vertex's outward normal. Nearest vertices are found once per
optimisation phase (:func:`find_contact_pairs`, a k-d tree without gradient)
and then held fixed, so the penalty is a smooth function of the parameters
during a line search, and each loss evaluation only touches the few pairs near
contact (:func:`contact_depth`) instead of every hand and face vertex.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree


class ContactPairs(NamedTuple):
    """Hand points near the face: frame (P,), point (P,) index into the hand
    point set, anchor (P,) index of the nearest face vertex; int64 tensors."""

    frame: torch.Tensor
    point: torch.Tensor
    anchor: torch.Tensor


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted outward unit normals (B, V, 3) of meshes (B, V, 3) with
    counter-clockwise faces (F, 3); vertices outside ``faces`` get zero normals."""
    tri = vertices[:, faces]  # (B, F, 3, 3)
    face_n = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    normals = torch.zeros_like(vertices).index_add_(1, faces.reshape(-1), face_n.repeat_interleave(3, dim=1))
    return torch.nn.functional.normalize(normals, dim=-1, eps=1e-12)


def find_contact_pairs(points: torch.Tensor, surface: torch.Tensor, radius: float) -> ContactPairs:
    """Pairs (frame, point, nearest surface vertex) for points within ``radius``
    (metres) of their nearest vertex; no gradient.

    Args: points (B, N, 3) hand points, surface (B, V, 3) face vertices, metres.
    """
    frames, idx, anchors = [], [], []
    for b, (s, p) in enumerate(zip(surface.detach().cpu().numpy(), points.detach().cpu().numpy())):
        dist, nearest = cKDTree(s).query(p, distance_upper_bound=radius, workers=1)
        near = np.flatnonzero(np.isfinite(dist))
        frames.append(np.full(len(near), b))
        idx.append(near)
        anchors.append(nearest[near])
    as_long = [
        torch.as_tensor(np.concatenate(x).astype(np.int64), device=points.device) for x in (frames, idx, anchors)
    ]
    return ContactPairs(*as_long)


def contact_depth(
    points: torch.Tensor, surface: torch.Tensor, faces: torch.Tensor, pairs: ContactPairs, radius: float
) -> torch.Tensor:
    """How deep (P,) metres, >= 0, each paired point lies behind the surface.

    Only a pair whose point is still within ``radius`` of its anchor counts, so
    the far side of a closed surface is never mistaken for its inside. Normals
    are computed on the faces around the anchors only. Differentiable in both
    point sets.

    Args: points (B, N, 3), surface (B, V, 3) metres, faces (F, 3) of the surface, pairs from
    :func:`find_contact_pairs`.
    """
    if pairs.frame.numel() == 0:
        return points.new_zeros(0)
    anchor_set = torch.zeros(surface.shape[1], dtype=torch.bool, device=faces.device)
    anchor_set[pairs.anchor] = True
    around = faces[anchor_set[faces].any(dim=1)]
    normal = vertex_normals(surface, around)[pairs.frame, pairs.anchor]
    offset = points[pairs.frame, pairs.point] - surface[pairs.frame, pairs.anchor]
    signed = (offset * normal).sum(-1)
    near = offset.norm(dim=-1) < radius
    return torch.where(near, torch.relu(-signed), torch.zeros_like(signed))
