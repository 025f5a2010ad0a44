"""Mesh queries used by the generator: normals, closest points, inside tests.

All functions take float64 CPU torch tensors in metres; vertices (V, 3), faces
(F, 3) int64. The winding number is :mod:`avatar.geometry.winding`'s.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from avatar.geometry.winding import winding_number


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (V, 3) (right-handed winding)."""
    tri = vertices[faces]
    face_n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = torch.zeros_like(vertices).index_add_(0, faces.reshape(-1), face_n.repeat_interleave(3, 0))
    return torch.nn.functional.normalize(normals, dim=1, eps=1e-12)


def _closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Closest points on triangles (a, b, c) to points p, all broadcast to
    (N, K, 3) -- Ericson, Real-Time Collision Detection, 5.1.5, vectorised."""
    a, b, c = torch.broadcast_tensors(a, b, c)
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    tiny = 1e-30
    # Interior by default, then override with the edge and vertex regions.
    denom = (va + vb + vc).clamp(min=tiny)
    v, w = vb / denom, vc / denom
    out = a + ab * v[..., None] + ac * w[..., None]
    bc_den = ((d4 - d3) + (d5 - d6)).clamp(min=tiny)
    t_bc = ((d4 - d3) / bc_den)[..., None]
    out = torch.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + (c - b) * t_bc, out)
    t_ac = (d2 / (d2 - d6).clamp(min=tiny))[..., None]
    out = torch.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * t_ac, out)
    t_ab = (d1 / (d1 - d3).clamp(min=tiny))[..., None]
    out = torch.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * t_ab, out)
    out = torch.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    out = torch.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = torch.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return out


def closest_points(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, candidates: int = 16
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest surface point of the mesh for each query point.

    Only the ``candidates`` triangles with the nearest centroids are tested
    (a k-d tree query), which is exact unless the mesh mixes very large and
    very small triangles; pass ``candidates >= F`` for a brute-force answer.

    Args:
        points: (N, 3) queries.

    Returns:
        closest: (N, 3) nearest points on the mesh.
        distance: (N,) unsigned distances.
        face: (N,) int64 index of the triangle holding the nearest point.
    """
    k = min(candidates, faces.shape[0])
    centroids = vertices[faces].mean(dim=1).numpy()
    _, idx = cKDTree(centroids).query(points.numpy(), k=k)
    idx = torch.as_tensor(np.asarray(idx, dtype=np.int64).reshape(points.shape[0], k))
    a, b, c = (vertices[faces[idx, j]] for j in range(3))  # (N, k, 3)
    cand = _closest_on_triangles(points[:, None], a, b, c)
    d2 = ((cand - points[:, None]) ** 2).sum(-1)
    best = d2.argmin(dim=1)
    rows = torch.arange(points.shape[0])
    return cand[rows, best], d2[rows, best].sqrt(), idx[rows, best]


def signed_distance(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, max_inside_depth: float = 0.015
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Signed distance (N,) to a closed, outward-oriented mesh (negative inside),
    the outward unit normal (N, 3) of the nearest triangle and the nearest
    surface points (N, 3).

    Inside means a generalised winding number above 1/2, which stays right for
    self-intersecting meshes (a posed hand whose curled fingers dip into the
    palm), where the nearest triangle's side would not. Points farther than
    ``max_inside_depth`` (metres) from the surface count as outside, which is
    exact for meshes thinner than twice that depth (a hand: ~3 cm).
    """
    closest, dist, face = closest_points(points, vertices, faces)
    tri = vertices[faces[face]]
    normal = torch.nn.functional.normalize(
        torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1, eps=1e-12
    )
    near = torch.nonzero(dist < max_inside_depth).squeeze(1)
    inside = torch.zeros(points.shape[0], dtype=torch.bool)
    inside[near] = winding_number(points[near], vertices, faces) > 0.5
    return torch.where(inside, -dist, dist), normal, closest
