"""A cheap differentiable signed-distance proxy for hand-face interpenetration."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted outward unit normals (B, V, 3) of meshes (B, V, 3) with
    counter-clockwise faces (F, 3)."""
    tri = vertices[:, faces]  # (B, F, 3, 3)
    face_n = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    normals = torch.zeros_like(vertices).index_add_(1, faces.reshape(-1), face_n.repeat_interleave(3, dim=1))
    return torch.nn.functional.normalize(normals, dim=-1, eps=1e-12)


def penetration_depth(points: torch.Tensor, surface: torch.Tensor, faces: torch.Tensor,
                      radius: float) -> torch.Tensor:
    """How deep (B, N) metres, >= 0, each point lies behind the surface.

    The proxy signed distance of a point is its offset from the nearest surface
    vertex along that vertex's outward normal; only points within ``radius``
    (metres) of their nearest vertex count, so the far side of a closed surface
    is never mistaken for its inside. The nearest vertex is found without
    gradient (k-d tree); the depth is differentiable in both point sets.

    Args: points (B, N, 3), surface (B, V, 3) metres, faces (F, 3) of the surface.
    """
    normals = vertex_normals(surface, faces)
    nearest = np.stack([
        cKDTree(s).query(p, workers=1)[1] for s, p in zip(surface.detach().cpu().numpy(), points.detach().cpu().numpy())
    ])
    idx = torch.as_tensor(nearest, device=points.device)[..., None].expand(-1, -1, 3)
    anchor, normal = surface.gather(1, idx), normals.gather(1, idx)
    offset = points - anchor
    signed = (offset * normal).sum(-1)
    near = offset.norm(dim=-1) < radius
    return torch.where(near, torch.relu(-signed), torch.zeros_like(signed))
