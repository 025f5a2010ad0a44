"""Edge adjacency of a triangle mesh and triangle walking of barycentric points (SplattingAvatar).

A Gaussian of :class:`avatar.representations.embedded.EmbeddedGaussians` lives at barycentric ``(u, v, w = 1 - u - v)``
of its triangle ``(v0, v1, v2)``. When an optimiser step takes it out of the triangle (a coordinate
below zero) :func:`walk` moves it across the crossed edge into the neighbouring triangle and
re-expresses its barycentrics there, hop after hop, until it lies inside.

How a hop works (all on the canonical mesh, float64):

- the crossed edge is the one opposite the most negative coordinate ``k`` (the edge through which the
  straight line from the triangle's centroid to the point leaves the triangle);
- the point is written in 2-D edge coordinates ``(s, h)``: ``s`` the distance along the edge from its
  first vertex ``i``, ``h`` the signed height towards the triangle's own apex ``k`` (negative outside);
- the neighbour is unfolded about the shared edge into the triangle's plane (an isometry of the
  neighbour: its apex goes to height ``-h_Q``), and the point's barycentrics are those of ``(s, h)`` in
  the unfolded neighbour. Edge points map exactly onto themselves, so the world position is
  continuous across the walk (the posed mesh is an affine image of each canonical triangle).

At a boundary edge (no neighbour) the point is projected orthogonally onto the edge's line
(``h = 0``); if that lies beyond the edge's end it keeps walking across the other crossed edge (so
a point can go round a boundary vertex), and after ``max_hops`` hops it is clamped into its current
triangle. Every returned point therefore lies on a valid triangle with ``u, v >= 0`` and
``u + v <= 1``.

Non-manifold edges (shared by more than two faces) connect each face to the next one sharing the
edge, in face order, cyclically (deterministic; every face gets a neighbour). A face never neighbours
a face on the same three vertices (a duplicate: that edge counts as a boundary), and edges with
coincident end vertices are boundaries.

SplattingAvatar itself (``model/simple_phongsurf/simple_phongsurf/src/triangle_walk.cpp`` in
``initialneil/SplattingAvatar``) builds the neighbour table from directed half-edges (so only
consistently oriented manifold pairs), walks a barycentric *shift* segment by segment, stops at the
intersection with a boundary edge, and carries the remaining shift into the neighbour by mirroring
barycentric coordinates (an affine map, not an isometric unfolding); it walks only the children of
split Gaussians (``splatting_avatar_model.py``: ``phongsurf.update_corres_spt``), since its
rendered position never depends on the ``uv`` part of ``_xyz``. Here every Gaussian that leaves its
triangle walks.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

#: a coordinate below ``-OUTSIDE_TOL`` counts as outside; smaller excursions are only clamped
OUTSIDE_TOL = 1e-9
_TINY = 1e-300


def edge_neighbours(faces: Tensor | np.ndarray) -> tuple[Tensor, Tensor]:
    """Neighbours across every edge of every face.

    The edge of face ``f`` in slot ``k`` is the one opposite its local vertex ``k``:
    ``(faces[f, (k + 1) % 3], faces[f, (k + 2) % 3])``.

    Args:
        faces: (F, 3) int vertex indices.
    Returns:
        neighbour: (F, 3) int64 face across each edge, -1 at a boundary.
        neighbour_slot: (F, 3) int64 slot of the same edge in the neighbour (its apex there), -1 at a
            boundary.
    """
    f = np.asarray(faces.cpu() if isinstance(faces, Tensor) else faces, dtype=np.int64)
    num = f.shape[0]
    first, second = f[:, [1, 2, 0]], f[:, [2, 0, 1]]
    lo, hi = np.minimum(first, second).ravel(), np.maximum(first, second).ravel()
    apex = f.ravel()
    order = np.lexsort((np.arange(3 * num), hi, lo))  # by edge, then by half-edge index (face order)
    lo_s, hi_s = lo[order], hi[order]
    starts = np.flatnonzero(np.r_[True, (lo_s[1:] != lo_s[:-1]) | (hi_s[1:] != hi_s[:-1])])
    sizes = np.diff(np.r_[starts, len(order)])
    partner = np.full(3 * num, -1, dtype=np.int64)
    pairs = starts[sizes == 2]
    a, b = order[pairs], order[pairs + 1]
    partner[a], partner[b] = b, a
    for start, size in zip(starts[sizes > 2], sizes[sizes > 2], strict=True):
        members = order[start : start + size]
        for pos, half in enumerate(members):
            partner[half] = members[(pos + 1) % size]
    # A partner on the same apex is a duplicate face (same three vertices); a degenerate edge has none.
    valid = (partner >= 0) & (lo != hi) & (apex != apex[np.maximum(partner, 0)])
    valid &= np.arange(3 * num) // 3 != np.maximum(partner, 0) // 3  # a degenerate face meets itself
    partner = np.where(valid, partner, -1)
    neighbour = np.where(partner >= 0, partner // 3, -1).reshape(num, 3)
    slot = np.where(partner >= 0, partner % 3, -1).reshape(num, 3)
    return torch.from_numpy(neighbour), torch.from_numpy(slot)


@dataclass
class WalkTable:
    """Everything a hop needs, per face and edge slot ``k`` (all (F, 3); lengths in canonical units).

    Attributes:
        neighbour: int64 face across the edge opposite vertex ``k``, -1 at a boundary.
        neighbour_apex: int64 local index of the neighbour's vertex off the shared edge.
        neighbour_first: int64 local index in the neighbour of this face's vertex ``(k + 1) % 3``.
        edge_length: float64 length ``L`` of the edge, from vertex ``i = (k + 1) % 3`` to ``j = (k + 2) % 3``.
        apex_along: float64 ``s`` of this face's apex ``k`` along the edge (from ``i``).
        apex_height: float64 height of this face's apex above the edge (> 0).
        neighbour_along: float64 ``s`` of the neighbour's apex along the same edge (from ``i``).
        neighbour_height: float64 height of the neighbour's apex above the edge (> 0).
    """

    neighbour: Tensor
    neighbour_apex: Tensor
    neighbour_first: Tensor
    edge_length: Tensor
    apex_along: Tensor
    apex_height: Tensor
    neighbour_along: Tensor
    neighbour_height: Tensor

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _along_and_height(start: Tensor, end: Tensor, point: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Edge length (...,), distance along the edge ``start -> end`` and height above its line of ``point``."""
    edge = end - start
    length = edge.norm(dim=-1)
    direction = edge / length.clamp_min(_TINY)[..., None]
    offset = point - start
    along = (offset * direction).sum(-1)
    height = (offset - along[..., None] * direction).norm(dim=-1)
    return length, along, height


def build_walk_table(vertices: Tensor, faces: Tensor) -> WalkTable:
    """The :class:`WalkTable` of the canonical mesh ``vertices`` (V, 3), ``faces`` (F, 3)."""
    faces = faces.long().cpu()
    verts = vertices.detach().cpu().double()
    neighbour, slot = edge_neighbours(faces)
    k = torch.arange(3)
    i_idx, j_idx = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]  # (F, 3) global ids of the edge ends
    start, end, own_apex = verts[i_idx], verts[j_idx], verts[faces]
    length, apex_along, apex_height = _along_and_height(start, end, own_apex)
    boundary = neighbour < 0
    nbr = neighbour.clamp_min(0)
    nbr_slot = slot.clamp_min(0)
    nbr_apex_vertex = faces[nbr, nbr_slot]
    _, nbr_along, nbr_height = _along_and_height(start, end, verts[nbr_apex_vertex])
    first_in_nbr = torch.where(faces[nbr, (nbr_slot + 1) % 3] == i_idx, (nbr_slot + 1) % 3, (nbr_slot + 2) % 3)
    minus = torch.full_like(neighbour, -1)
    return WalkTable(
        neighbour=neighbour,
        neighbour_apex=torch.where(boundary, minus, nbr_slot),
        neighbour_first=torch.where(boundary, minus, first_in_nbr),
        edge_length=length,
        apex_along=apex_along,
        apex_height=apex_height,
        neighbour_along=torch.where(boundary, torch.zeros_like(nbr_along), nbr_along),
        neighbour_height=torch.where(boundary, torch.ones_like(nbr_height), nbr_height),
    )


def full_barycentric(uv: Tensor) -> Tensor:
    """(N, 2) ``(u, v)`` -> (N, 3) ``(u, v, 1 - u - v)``."""
    return torch.cat([uv, 1.0 - uv.sum(-1, keepdim=True)], dim=-1)


def clamp_into_triangle(bary: Tensor) -> Tensor:
    """(N, 3) barycentrics with negative coordinates set to 0 and renormalised to sum 1
    (the centroid where all are <= 0)."""
    clamped = bary.clamp_min(0.0)
    total = clamped.sum(-1, keepdim=True)
    centroid = torch.full_like(bary, 1.0 / 3.0)
    return torch.where(total > 0, clamped / total.clamp_min(_TINY), centroid)


def _hop(table: WalkTable, tri: Tensor, bary: Tensor) -> tuple[Tensor, Tensor]:
    """One hop of the points (M,) on triangles ``tri`` at (M, 3) float64 ``bary`` that lie outside:
    across the edge opposite their most negative coordinate (or onto it at a boundary)."""
    k = bary.argmin(-1)
    rows = torch.arange(len(tri), device=tri.device)
    i, j = (k + 1) % 3, (k + 2) % 3
    length = table.edge_length[tri, k].clamp_min(_TINY)
    s = bary[rows, j] * length + bary[rows, k] * table.apex_along[tri, k]
    h = bary[rows, k] * table.apex_height[tri, k]  # < 0: beyond the edge
    # Boundary: orthogonal projection onto the edge's line, in the same triangle.
    on_line = torch.zeros_like(bary)
    on_line[rows, j] = s / length
    on_line[rows, i] = 1.0 - s / length
    # Neighbour: (s, h) in the neighbour unfolded about the shared edge.
    height = table.neighbour_height[tri, k].clamp_min(_TINY)
    gamma = -h / height
    beta = (s - gamma * table.neighbour_along[tri, k]) / length
    alpha = 1.0 - beta - gamma
    nbr = table.neighbour[tri, k]
    boundary = nbr < 0
    apex = torch.where(boundary, 0, table.neighbour_apex[tri, k])  # any valid slots at a boundary
    first = torch.where(boundary, 1, table.neighbour_first[tri, k])
    crossed = torch.zeros_like(bary)
    crossed[rows, apex] = gamma
    crossed[rows, first] = alpha
    crossed[rows, 3 - apex - first] = beta
    return torch.where(boundary, tri, nbr), torch.where(boundary[:, None], on_line, crossed)


def walk(table: WalkTable, triangle: Tensor, uv: Tensor, max_hops: int = 64) -> tuple[Tensor, Tensor]:
    """Walk every point that left its triangle until it lies inside one.

    Args:
        table: the canonical mesh's :class:`WalkTable`.
        triangle: (N,) int64 current triangle of each point.
        uv: (N, 2) barycentric ``(u, v)`` (``w = 1 - u - v``), possibly outside the triangle.
        max_hops: bound on hops per point; a point still outside after them is clamped into its
            current triangle.
    Returns:
        (N,) int64 triangles and (N, 2) ``uv`` (dtype of ``uv``) with ``u, v >= 0`` and ``u + v <= 1``.
    """
    tri = triangle.clone()
    bary = full_barycentric(uv.detach().double())
    touched = bary.min(-1).values < 0
    active = torch.nonzero(bary.min(-1).values < -OUTSIDE_TOL).flatten()
    for _ in range(max_hops):
        if len(active) == 0:
            break
        new_tri, new_bary = _hop(table, tri[active], bary[active])
        tri[active], bary[active] = new_tri, new_bary
        still = new_bary.min(-1).values < -OUTSIDE_TOL
        active = active[still]
    # Only points that were outside change (inside ones keep their exact values).
    out = uv.detach().clone()
    out[touched] = clamp_into_triangle(bary[touched])[:, :2].to(uv.dtype)
    return tri, out
