"""Hand-mesh queries for the contact solver: closest surface points and an inside test, in torch.

Points are (N, 3), mesh vertices (Vh, 3) and faces (F, 3) int64, all on one device and dtype.
The closest point is found exactly on the ``candidates`` triangles whose centroids are nearest
(a top-k over one (N, F) distance matrix, no k-d tree, so it runs on any torch device); pass
``candidates >= F`` for the brute-force answer. The inside test is the generalised winding
number (Jacobson et al. 2013), which stays right for a posed hand whose curled fingers dip into
the palm, where the side of the nearest triangle would not.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from avatar.geometry.winding import winding_number

#: Points this close to the hand surface (metres) always take the winding-number test.
AMBIGUOUS_BAND_M = 0.005


class HandQuery(NamedTuple):
    """Per query point: ``closest`` (N, 3) point on the hand surface, ``distance`` (N,) to it,
    ``inside`` (N,) bool (inside the hand)."""

    closest: torch.Tensor
    distance: torch.Tensor
    inside: torch.Tensor

    @property
    def depth(self) -> torch.Tensor:
        """(N,) penetration depth: the distance for points inside the hand, else 0."""
        return torch.where(self.inside, self.distance, torch.zeros_like(self.distance))


def _closest_on_segments(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Closest points (..., 3) on segments a-b to points p (all broadcast to (..., 3))."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)
    return a + t.clamp(0.0, 1.0)[..., None] * ab


def closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Closest points (..., 3) on triangles (a, b, c) to points p, all broadcast to (..., 3).

    The projection onto the triangle's plane when its barycentric coordinates are all
    non-negative, else the nearest of the closest points on the three edges (degenerate
    triangles always take the edge path)."""
    p, a, b, c = torch.broadcast_tensors(p, a, b, c)
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d20, d21 = (ap * ab).sum(-1), (ap * ac).sum(-1)
    denom = d00 * d11 - d01 * d01
    ok = denom > 1e-12 * (d00 * d11).clamp_min(1e-300)
    safe = torch.where(ok, denom, torch.ones_like(denom))
    v = (d11 * d20 - d01 * d21) / safe
    w = (d00 * d21 - d01 * d20) / safe
    interior = ok & (v >= 0) & (w >= 0) & (v + w <= 1)
    on_plane = a + v[..., None] * ab + w[..., None] * ac
    edges = torch.stack(
        [_closest_on_segments(p, a, b), _closest_on_segments(p, b, c), _closest_on_segments(p, c, a)], dim=-2
    )  # (..., 3 edges, 3)
    best = ((edges - p[..., None, :]) ** 2).sum(-1).argmin(-1, keepdim=True)
    on_edge = torch.take_along_dim(edges, best[..., None], dim=-2).squeeze(-2)
    return torch.where(interior[..., None], on_plane, on_edge)


def closest_on_mesh(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, candidates: int = 16
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest surface points (N, 3), distances (N,) and the index (N,) int64 of the triangle holding
    each, for points (N, 3) and a triangle mesh."""
    if points.shape[0] == 0:
        return points.clone(), points.new_zeros(0), torch.zeros(0, dtype=torch.int64, device=points.device)
    tri = vertices[faces]  # (F, 3, 3)
    k = min(candidates, faces.shape[0])
    idx = torch.cdist(points, tri.mean(dim=1)).topk(k, dim=1, largest=False).indices  # (N, k)
    cand = closest_on_triangles(points[:, None], tri[idx, 0], tri[idx, 1], tri[idx, 2])  # (N, k, 3)
    d2 = ((cand - points[:, None]) ** 2).sum(-1)
    best = d2.argmin(dim=1)
    rows = torch.arange(points.shape[0], device=points.device)
    return cand[rows, best], d2[rows, best].sqrt(), idx[rows, best]


def query_hand(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, max_depth: float) -> HandQuery:
    """Closest hand points and the inside test for points (N, 3).

    The winding number costs N x F, so only points that may be inside take it: within
    ``max_depth`` (metres) of the surface (a hand is about 3 cm thick, so no surface point lies
    deeper), and either behind their nearest triangle or within :data:`AMBIGUOUS_BAND_M` of the
    surface, where curled fingers dipping into the palm make the side of the nearest triangle
    unreliable. It runs in float32: only its comparison with 1/2 matters."""
    closest, distance, face = closest_on_mesh(points, vertices, faces)
    tri = vertices[faces[face]]
    normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1)
    behind = ((points - closest) * normal).sum(1) < 0
    inside = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    test = torch.nonzero((distance < max_depth) & (behind | (distance < AMBIGUOUS_BAND_M))).squeeze(1)
    if test.numel():
        inside[test] = winding_number(points[test].float(), vertices.float(), faces) > 0.5
    return HandQuery(closest, distance, inside)
