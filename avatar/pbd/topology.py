"""Mesh topology for the constraints: unique edges, bending stencils and a greedy constraint colouring."""

from __future__ import annotations

import numpy as np
import torch


def unique_edges(faces: torch.Tensor) -> torch.Tensor:
    """(E, 2) int64 vertex pairs (smaller index first) of the triangles (F, 3)."""
    pairs = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return torch.unique(pairs.sort(dim=1).values, dim=0)


def bending_stencils(faces: torch.Tensor) -> torch.Tensor:
    """(B, 4) int64 ``[x0, x1, x2, x3]`` for every interior edge x0-x1 shared by exactly two
    triangles (x0, x1, x2) and (x1, x0, x3); x2 and x3 are the vertices opposite the edge."""
    f = faces.cpu().numpy()
    tri = np.repeat(np.arange(len(f)), 3)
    a = f[:, [0, 1, 2]].reshape(-1)
    b = f[:, [1, 2, 0]].reshape(-1)
    opposite = f[:, [2, 0, 1]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo.astype(np.int64) * (int(f.max(initial=0)) + 1) + hi
    order = np.argsort(key, kind="stable")
    key, lo, hi, opposite, tri = key[order], lo[order], hi[order], opposite[order], tri[order]
    _, start, count = np.unique(key, return_index=True, return_counts=True)
    two = start[count == 2]  # manifold interior edges; boundary and non-manifold edges are skipped
    out = np.stack([lo[two], hi[two], opposite[two], opposite[two + 1]], axis=1)
    return torch.as_tensor(out, dtype=torch.int64, device=faces.device)


def colour_constraints(vertex_sets: torch.Tensor) -> list[torch.Tensor]:
    """Greedy colouring of constraints (M, K) given by the vertices they touch: constraints of one
    colour share no vertex, so a colour can be projected at once, exactly as Gauss-Seidel would.

    Returns the row indices (int64) of each colour, in colour order."""
    rows = vertex_sets.cpu().numpy()
    used: dict[int, set[int]] = {}
    colour = np.empty(len(rows), dtype=np.int64)
    for m, verts in enumerate(rows):
        taken = set().union(*(used.get(int(v), set()) for v in verts))
        c = next(i for i in range(len(taken) + 1) if i not in taken)
        colour[m] = c
        for v in verts:
            used.setdefault(int(v), set()).add(c)
    return [
        torch.as_tensor(np.flatnonzero(colour == c), device=vertex_sets.device)
        for c in range(int(colour.max(initial=-1)) + 1)
    ]
