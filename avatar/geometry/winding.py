"""The generalised winding number of a triangle mesh at points (Jacobson et al. 2013): the inside test of the
contact solver and the synthetic generator. The all-pairs sum is chunked over points to bound memory."""

from __future__ import annotations

import torch

_CHUNK_PAIRS = 1 << 21


def winding_number(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Generalised winding number (N,) of the mesh at the points (Jacobson et al.
    2013): ~1 inside a closed outward-oriented mesh, ~0 outside, graceful for
    meshes with holes (such as the open wrist of a hand)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    step = max(1, _CHUNK_PAIRS // max(1, faces.shape[0]))
    out = []
    for start in range(0, points.shape[0], step):
        p = points[start : start + step, None]
        ra, rb, rc = a - p, b - p, c - p
        la, lb, lc = ra.norm(dim=-1), rb.norm(dim=-1), rc.norm(dim=-1)
        det = (ra * torch.linalg.cross(rb, rc, dim=-1)).sum(-1)
        den = la * lb * lc + (ra * rb).sum(-1) * lc + (rb * rc).sum(-1) * la + (rc * ra).sum(-1) * lb
        out.append(torch.atan2(det, den).sum(dim=1) / (2 * torch.pi))
    return torch.cat(out) if out else points.new_zeros((0,))
