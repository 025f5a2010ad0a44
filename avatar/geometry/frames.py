"""Local frames of mesh triangles, and Gaussians expressed in them (GaussianAvatars binding).

For a triangle (v0, v1, v2) the frame is

- origin ``T``: the centroid;
- rotation ``R`` with columns ``a0 = (v1 - v0)/|v1 - v0|`` (first edge),
  ``a1 = normalise(a0 x (v2 - v0))`` (the normal) and ``a2 = normalise(a0 x a1)``
  (in the triangle plane, perpendicular to the first edge, pointing away from v2);
- scale ``k = (|v1 - v0| + |a2 . (v2 - v0)|) / 2`` (mean of base and height).

A Gaussian with local mean ``mu_i``, scale ``s_i`` and rotation ``q_i`` is placed at
``mu = k R mu_i + T``, ``s = k s_i``, ``q = R q_i``.

Degenerate triangles (coincident vertices, zero area) get a finite frame: the
edge falls back to another edge or the x axis, the normal to any direction
perpendicular to it, and ``k`` is clamped to ``min_scale``. Nothing is NaN,
values or gradients.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from avatar.geometry.gather import gather_rows

_EPS = 1e-12


@dataclass
class TriangleFrames:
    """Frames of F triangles: ``origin`` (F, 3), ``rotation`` (F, 3, 3) (columns a0, a1, a2), ``scale`` (F,)."""

    origin: Tensor
    rotation: Tensor
    scale: Tensor


def _normalise(v: Tensor, fallback: Tensor) -> Tensor:
    """v / |v| where |v| is not tiny, else ``fallback`` (already unit); gradient-safe."""
    norm2 = (v * v).sum(-1, keepdim=True)
    ok = norm2 > _EPS
    safe = torch.where(ok, v, torch.ones_like(v)) / torch.sqrt(torch.where(ok, norm2, torch.ones_like(norm2)))
    return torch.where(ok, safe, fallback)


def _any_perpendicular(a: Tensor) -> Tensor:
    """A unit vector perpendicular to each unit vector in ``a`` (..., 3)."""
    helper = torch.zeros_like(a)
    smallest = a.abs().argmin(-1, keepdim=True)
    helper.scatter_(-1, smallest, 1.0)
    return _normalise(torch.linalg.cross(a, helper), torch.zeros_like(a) + a.new_tensor([0.0, 0.0, 1.0]))


def triangle_frames(vertices: Tensor, faces: Tensor, min_scale: float = 1e-6) -> TriangleFrames:
    """Frames of every face.

    Args:
        vertices: (..., V, 3) float vertex positions (any batch dims).
        faces: (F, 3) int64 vertex indices.
        min_scale: lower bound on ``k`` so degenerate triangles keep finite, non-zero Gaussians.
    Returns:
        :class:`TriangleFrames` with shapes (..., F, 3), (..., F, 3, 3), (..., F).
    """
    tri = gather_rows(vertices, faces, dim=-2)  # (..., F, 3, 3); vertices[..., faces, :], reproducible backward
    v0, v1, v2 = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    e1, e2 = v1 - v0, v2 - v0
    x_axis = torch.zeros_like(e1) + e1.new_tensor([1.0, 0.0, 0.0])
    a0 = _normalise(e1, _normalise(e2, x_axis))
    perpendicular = _any_perpendicular(a0)  # the fallback of both: a normal for a degenerate triangle
    a1 = _normalise(torch.linalg.cross(a0, e2), perpendicular)
    a2 = _normalise(torch.linalg.cross(a0, a1), perpendicular)
    # a2 = a0 x a1 lies in the triangle plane, perpendicular to the first edge, pointing away from v2
    # (as in GaussianAvatars: a2 = -normalise(a1 x a0)).
    rotation = torch.stack([a0, a1, a2], dim=-1)
    base = torch.sqrt((e1 * e1).sum(-1) + _EPS)
    height = ((a2 * e2).sum(-1)).abs()
    scale = torch.clamp((base + height) / 2, min=min_scale)
    return TriangleFrames(origin=tri.mean(dim=-2), rotation=rotation, scale=scale)


def rotation_to_quaternion(R: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (w, x, y, z), w >= 0; NaN-free."""
    m = R
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = torch.stack(
        [
            1.0 + trace,
            1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        dim=-1,
    )
    best = candidates.argmax(-1)
    s = torch.sqrt(torch.clamp(candidates.gather(-1, best[..., None]), min=_EPS))[..., 0] * 2  # 4 * |component|
    w = torch.stack(
        [
            s / 4,
            (m[..., 2, 1] - m[..., 1, 2]) / s,
            (m[..., 0, 2] - m[..., 2, 0]) / s,
            (m[..., 1, 0] - m[..., 0, 1]) / s,
        ],
        -1,
    )
    x = torch.stack(
        [
            (m[..., 2, 1] - m[..., 1, 2]) / s,
            s / 4,
            (m[..., 0, 1] + m[..., 1, 0]) / s,
            (m[..., 0, 2] + m[..., 2, 0]) / s,
        ],
        -1,
    )
    y = torch.stack(
        [
            (m[..., 0, 2] - m[..., 2, 0]) / s,
            (m[..., 0, 1] + m[..., 1, 0]) / s,
            s / 4,
            (m[..., 1, 2] + m[..., 2, 1]) / s,
        ],
        -1,
    )
    z = torch.stack(
        [
            (m[..., 1, 0] - m[..., 0, 1]) / s,
            (m[..., 0, 2] + m[..., 2, 0]) / s,
            (m[..., 1, 2] + m[..., 2, 1]) / s,
            s / 4,
        ],
        -1,
    )
    q = torch.where(
        (best == 0)[..., None], w, torch.where((best == 1)[..., None], x, torch.where((best == 2)[..., None], y, z))
    )
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def place_means(
    frames: TriangleFrames, binding: Tensor, local_means: Tensor, local_scales: Tensor
) -> tuple[Tensor, Tensor]:
    """World means (..., N, 3) and scales (..., N, 3) of bound Gaussians: :func:`place_gaussians` without the
    rotations, for callers that need only where the Gaussians are and how large (the arguments as there)."""
    # gathered with a reproducible backward (gather_rows): a triangle's Gaussians share its frame, and with the
    # tracking refined the frames' gradients sum over them
    R = gather_rows(frames.rotation, binding, dim=-3)
    k = gather_rows(frames.scale, binding, dim=-1)[..., None]
    means = k * (R @ local_means[..., None])[..., 0] + gather_rows(frames.origin, binding, dim=-2)
    return means, k * local_scales


def place_gaussians(
    frames: TriangleFrames, binding: Tensor, local_means: Tensor, local_scales: Tensor, local_quats: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """World means (..., N, 3), scales (..., N, 3) and quaternions (..., N, 4) of bound Gaussians.

    Args:
        frames: frames of the F triangles, batch dims (...).
        binding: (N,) int64 parent triangle of each Gaussian.
        local_means: (N, 3) mean in the parent frame, in units of the frame scale k.
        local_scales: (N, 3) linear scale in units of k.
        local_quats: (N, 4) rotation relative to the frame (need not be normalised).
    """
    means, scales = place_means(frames, binding, local_means, local_scales)
    # per triangle, then gathered: the same values as per Gaussian, bit for bit, for fewer conversions (one
    # draft warm-up step: 2.5 ms for 11k triangles instead of 9.8 ms for their 36k Gaussians, 1 thread)
    frame_quats = gather_rows(rotation_to_quaternion(frames.rotation), binding, dim=-2)
    return means, scales, quaternion_multiply(frame_quats, local_quats)
