"""The generator's own soft-tissue model: how the face gives way under a hand.

Physical picture: the skin is a membrane under tension lying on a Winkler foundation (the
subcutaneous tissue: independent springs whose stiffness is inversely proportional to the
tissue's thickness over the bone), pressed by a rigid hand with frictionless, one-sided
(Signorini) contact. Where the hand pushes, the skin conforms to the hand's surface; around the
contact the membrane drags its neighbours into a dent that decays over a length
``l_i = DENT_DECAY_M * sqrt(kappa_i)``, long over thick tissue (cheeks) and short over bone
(forehead, nose bridge), so thin tissue only yields where it is touched. Like an elastic
half-space under a sphere (Hertz), the skin may lift off the hand near the rim of the geometric
overlap, where the tension holds it below the hand's curving surface: a vertex with a gap there
is not pushed by the hand (its contact force would be negative).

This is deliberately *not* position-based dynamics (the method under test uses PBD): each vertex
moves along one fixed direction, the energy is a scalar membrane-plus-foundation quadratic, and
the contact problem is solved exactly.

1. Penetration: every face vertex inside the posed hand mesh (a generalised winding number) has
   exit vector ``e_j`` to the nearest hand surface point; it may move along ``n_j = e_j / |e_j|``
   and must move at least ``delta_j = |e_j| + CLEARANCE_M`` (no vertex ends inside the hand).
2. Region: vertices within ``REACH_M`` of a penetrating vertex (Euclidean on the undeformed
   face) move along the direction ``n_i = normalize(sum_j g_ij delta_j n_j)``, ``g`` a Gaussian
   of width ``DIRECTION_SIGMA_M``; every other vertex stays exactly where it is.
3. Magnitudes ``w`` (metres) minimise ``1/2 sum_edges (w_a - w_b)^2 / |e|^2 + 1/2 sum_i k_i w_i^2``
   with ``k_i = 3 / (2 l_i^2)`` (the triangle lattice's Laplacian is 3/2 of the continuum's), subject
   to ``w_j >= delta_j`` on the penetrating vertices. The matrix is an M-matrix, so the contact set
   is found exactly by releasing, round after round, the vertices whose contact force is negative
   (monotone: the dent only deepens, no constraint is ever violated again).
4. A few re-projection passes move any vertex the dent carried into another part of the hand to
   its nearest hand surface point plus the clearance; one still inside after them (skin wedged
   between two fingers) moves to the nearest point just outside the hand.

Offsets are exactly zero for vertices farther than ``REACH_M`` from every penetrating vertex,
hence exactly zero in frames without contact.
"""

from __future__ import annotations

import torch

from avatar.synthetic.geometry import signed_distance, vertex_normals

#: Decay length of the dent over fully compliant tissue (metres).
DENT_DECAY_M = 0.010
#: Vertices farther than this from every penetrating vertex never move (metres).
REACH_M = 0.030
#: Width of the Gaussian that smooths the push direction around the contact (metres).
DIRECTION_SIGMA_M = 0.010
#: Skin-to-bone distance at which the tissue is fully compliant (metres).
THICK_TISSUE_M = 0.018
KAPPA_MIN = 0.1
#: Vertices in contact end this far outside the hand surface (metres).
CLEARANCE_M = 0.0003
PASSES = 6
#: Contact forces above -this count as pushing (relative to the largest force).
_RELEASE_TOLERANCE = 1e-12


def compliance(inner_distance: torch.Tensor) -> torch.Tensor:
    """Per-vertex compliance in [KAPPA_MIN, 1] from skin-to-bone distance (V,) metres."""
    return (inner_distance / THICK_TISSUE_M).clamp(KAPPA_MIN, 1.0)


def _near_hand(face: torch.Tensor, hand: torch.Tensor, margin: float) -> torch.Tensor:
    """Indices of face vertices inside the hand's bounding box grown by margin."""
    lo = hand.amin(dim=0) - margin
    hi = hand.amax(dim=0) + margin
    return torch.nonzero(((face >= lo) & (face <= hi)).all(dim=1)).squeeze(1)


def membrane_matrix(
    vertices: torch.Tensor, faces: torch.Tensor, region: torch.Tensor, inner_distance: torch.Tensor
) -> torch.Tensor:
    """Hessian (n, n) of the membrane-plus-foundation energy over the ``region`` vertices (n,).

    Vertices outside the region are held at zero: an edge to one adds its spring to the diagonal.
    """
    n = region.numel()
    local = torch.full((vertices.shape[0],), -1, dtype=torch.int64)
    local[region] = torch.arange(n)
    edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values.unique(dim=0)
    a, b = local[edges[:, 0]], local[edges[:, 1]]
    touching = (a >= 0) | (b >= 0)
    edges, a, b = edges[touching], a[touching], b[touching]
    weight = 1.0 / ((vertices[edges[:, 0]] - vertices[edges[:, 1]]) ** 2).sum(dim=1).clamp(min=1e-12)
    decay = DENT_DECAY_M * compliance(inner_distance[region]).sqrt()
    hessian = torch.diag(1.5 / decay**2)
    for end, other in ((a, b), (b, a)):
        inside = end >= 0
        hessian.index_put_((end[inside], end[inside]), weight[inside], accumulate=True)
        both = inside & (other >= 0)
        hessian.index_put_((end[both], other[both]), -weight[both], accumulate=True)
    return hessian


def signorini_magnitudes(hessian: torch.Tensor, pressed: torch.Tensor, minimum: torch.Tensor) -> torch.Tensor:
    """Minimiser (n,) of ``1/2 w^T H w`` subject to ``w[pressed] >= minimum`` for an M-matrix ``H``.

    Starts with every pressed vertex in contact and releases, each round, those whose contact force
    ``(H w)_j`` is negative; by the M-matrix comparison principle the free values only grow, so the
    bounds stay satisfied and at most ``len(pressed)`` rounds are needed.
    """
    n = hessian.shape[0]
    active = torch.zeros(n, dtype=torch.bool)
    active[pressed] = True
    bound = torch.zeros(n, dtype=hessian.dtype)
    bound[pressed] = minimum
    for _ in range(pressed.numel() + 1):
        free = ~active
        w = torch.where(active, bound, torch.zeros_like(bound))
        if free.any():
            rhs = -hessian[free][:, active] @ bound[active]
            w[free] = torch.linalg.solve(hessian[free][:, free], rhs)
        force = hessian @ w
        scale = force[active].abs().max().clamp(min=1e-300) if active.any() else 1.0
        release = active & (force < -_RELEASE_TOLERANCE * scale)
        if not release.any():
            return w
        active &= ~release
    raise RuntimeError("signorini_magnitudes: the contact set did not settle (is the matrix an M-matrix?)")


def contact_offsets(
    face_vertices: torch.Tensor,
    face_faces: torch.Tensor,
    inner_distance: torch.Tensor,
    hand_vertices: torch.Tensor,
    hand_faces: torch.Tensor,
) -> torch.Tensor:
    """Soft-tissue displacement of the face for one frame.

    Args:
        face_vertices: (V, 3) float64 posed face, world metres.
        face_faces: (F, 3) int64 face triangles.
        inner_distance: (V,) skin-to-bone distance, metres.
        hand_vertices: (Vh, 3) float64 posed hand, world metres.
        hand_faces: (Fh, 3) int64 hand triangles (outward-oriented).

    Returns:
        (V, 3) float64 offsets, world metres; all zero when the hand does not
        penetrate the face.
    """
    offsets = torch.zeros_like(face_vertices)
    near = _near_hand(face_vertices, hand_vertices, REACH_M)
    if near.numel() == 0:
        return offsets
    sdf, _, closest = signed_distance(face_vertices[near], hand_vertices, hand_faces)
    inside = sdf < 0
    if not inside.any():
        return offsets
    sources = near[inside]
    depth = -sdf[inside]
    exit_dir = (closest[inside] - face_vertices[sources]) / depth[:, None].clamp(min=1e-12)
    d2 = torch.cdist(face_vertices, face_vertices[sources]) ** 2  # (V, c)
    region = torch.nonzero((d2 < REACH_M**2).any(dim=1)).squeeze(1)
    g = torch.exp(-d2[region] / (2 * DIRECTION_SIGMA_M**2))
    direction = torch.nn.functional.normalize(g @ (depth[:, None] * exit_dir), dim=1, eps=1e-12)
    pressed = torch.searchsorted(region, sources)
    direction[pressed] = exit_dir
    hessian = membrane_matrix(face_vertices, face_faces, region, inner_distance)
    magnitude = signorini_magnitudes(hessian, pressed, depth + CLEARANCE_M)
    local = magnitude[:, None] * direction
    x = face_vertices[region]
    for _ in range(PASSES):
        moved = x + local
        sdf, _, closest = signed_distance(moved, hand_vertices, hand_faces)
        still = sdf < 0
        if not still.any():
            break
        to_surface = closest - moved  # |to_surface| = -sdf > 0 where still inside
        local = local + still[:, None] * to_surface * (1 + CLEARANCE_M / (-sdf).clamp(min=1e-12))[:, None]
    else:
        stuck = torch.nonzero(signed_distance(x + local, hand_vertices, hand_faces)[0] < 0).squeeze(1)
        local[stuck] = _nearest_outside(x[stuck] + local[stuck], hand_vertices, hand_faces) - x[stuck]
    offsets[region] = local
    return offsets


def _nearest_outside(points: torch.Tensor, hand_vertices: torch.Tensor, hand_faces: torch.Tensor) -> torch.Tensor:
    """For points (n, 3) inside the hand where projecting onto the nearest surface does not get them out (skin
    wedged between two fingers, whose nearest surface point on one lies inside the other), the nearest
    point (n, 3) just outside the hand: a vertex, edge midpoint or triangle centroid of the hand pushed out
    by the clearance along its normal, among those near the points that lie outside every finger."""
    if points.shape[0] == 0:
        return points
    tri = hand_vertices[hand_faces]  # (F, 3, 3)
    face_normal = torch.nn.functional.normalize(
        torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1, eps=1e-12
    )
    normal = vertex_normals(hand_vertices, hand_faces)
    edges = torch.cat([hand_faces[:, [0, 1]], hand_faces[:, [1, 2]], hand_faces[:, [2, 0]]])
    samples = torch.cat(
        [
            hand_vertices + CLEARANCE_M * normal,
            tri.mean(dim=1) + CLEARANCE_M * face_normal,
            hand_vertices[edges].mean(dim=1)
            + CLEARANCE_M * torch.nn.functional.normalize(normal[edges].sum(dim=1), dim=1, eps=1e-12),
        ]
    )
    distance = torch.cdist(points, samples)  # (n, s)
    for radius in (0.25 * REACH_M, REACH_M):
        near = (distance < radius).any(dim=0)
        outside = signed_distance(samples[near], hand_vertices, hand_faces)[0] >= 0
        if outside.any():
            candidates = torch.nonzero(near).squeeze(1)[outside]
            return samples[candidates[distance[:, candidates].argmin(dim=1)]]
    raise RuntimeError(
        f"soft tissue: no point outside the hand within {REACH_M * 1e3:.0f} mm of a face vertex inside it"
    )
