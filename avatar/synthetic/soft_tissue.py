"""The generator's own soft-tissue model: how the face gives way under a hand.

This is deliberately *not* position-based dynamics (the method under test uses
PBD); it is a closed-form displacement field:

1. Penetration: every face vertex inside the posed hand mesh has depth
   ``p_j = -sdf_hand(x_j) > 0`` and contact normal ``n_j`` (outward normal of
   the nearest hand triangle).
2. Spread: the dent reaches around the contact with a Gaussian falloff in
   distance (Euclidean on the undeformed face, a stand-in for surface distance
   over the few centimetres involved), truncated at ``3 sigma``:
   ``D_i = max_j p_j g(|x_i - x_j|)``, direction ``n_i = normalize(sum_j g p_j n_j)``.
3. Compliance: ``kappa_i = clip(inner_distance_i / THICK_TISSUE_M, KAPPA_MIN, 1)``,
   so thick tissue (cheeks) carries a wide dent and thin tissue over bone
   (forehead, nose bridge) only yields where it is touched.
   Magnitude ``m_i = max(p_i, kappa_i D_i)``; offset ``m_i n_i``.
4. A few re-projection passes move any vertex still inside the hand to its
   nearest hand surface point (plus a small clearance), so the final face does
   not interpenetrate the hand.

Offsets are exactly zero for vertices farther than ``3 sigma`` from every
penetrating vertex, hence exactly zero in frames without contact.
"""

from __future__ import annotations

import torch

from avatar.synthetic.geometry import signed_distance

FALLOFF_SIGMA_M = 0.010
THICK_TISSUE_M = 0.018
KAPPA_MIN = 0.1
#: Vertices are pushed this far outside the hand surface (metres).
CLEARANCE_M = 0.0003
PASSES = 6


def compliance(inner_distance: torch.Tensor) -> torch.Tensor:
    """Per-vertex compliance in [KAPPA_MIN, 1] from skin-to-bone distance (V,) metres."""
    return (inner_distance / THICK_TISSUE_M).clamp(KAPPA_MIN, 1.0)


def _near_hand(face: torch.Tensor, hand: torch.Tensor, margin: float) -> torch.Tensor:
    """Indices of face vertices inside the hand's bounding box grown by margin."""
    lo = hand.amin(dim=0) - margin
    hi = hand.amax(dim=0) + margin
    return torch.nonzero(((face >= lo) & (face <= hi)).all(dim=1)).squeeze(1)


def contact_offsets(face_vertices: torch.Tensor, inner_distance: torch.Tensor,
                    hand_vertices: torch.Tensor, hand_faces: torch.Tensor) -> torch.Tensor:
    """Soft-tissue displacement of the face for one frame.

    Args:
        face_vertices: (V, 3) float64 posed face, world metres.
        inner_distance: (V,) skin-to-bone distance, metres.
        hand_vertices: (Vh, 3) float64 posed hand, world metres.
        hand_faces: (Fh, 3) int64 hand triangles (outward-oriented).

    Returns:
        (V, 3) float64 offsets, world metres; all zero when the hand does not
        penetrate the face.
    """
    offsets = torch.zeros_like(face_vertices)
    sigma = FALLOFF_SIGMA_M
    idx = _near_hand(face_vertices, hand_vertices, 3 * sigma)
    if idx.numel() == 0:
        return offsets
    x = face_vertices[idx]
    sdf, normal, _ = signed_distance(x, hand_vertices, hand_faces)
    inside = sdf < 0
    if not inside.any():
        return offsets
    depth = (-sdf).clamp(min=0)
    src = torch.nonzero(inside).squeeze(1)
    d2 = torch.cdist(x, x[src]) ** 2  # (n, c)
    g = torch.exp(-d2 / (2 * sigma**2)) * (d2 < (3 * sigma) ** 2)
    spread = (g * depth[src]).amax(dim=1)
    direction = torch.nn.functional.normalize(g @ (depth[src, None] * normal[src]), dim=1, eps=1e-12)
    magnitude = torch.maximum(depth, compliance(inner_distance[idx]) * spread)
    magnitude = torch.where(magnitude > 0, magnitude + CLEARANCE_M * inside, magnitude)
    local = magnitude[:, None] * direction
    for _ in range(PASSES):
        moved = x + local
        sdf, _, closest = signed_distance(moved, hand_vertices, hand_faces)
        still = (sdf < 0)[:, None]
        if not still.any():
            break
        exit_vec = closest - moved  # towards the surface; |exit| = -sdf > 0 where still inside
        local = local + still * exit_vec * (1 + CLEARANCE_M / (-sdf).clamp(min=1e-12))[:, None]
    offsets[idx] = local
    return offsets
