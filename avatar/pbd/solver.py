"""XPBD contact solve of the face against the kinematic hand, one frame at a time.

Per frame (:func:`solve_frame`), on the posed, undeformed face ``rest`` (V, 3):

1. Face vertices inside the hand's bounding box grown by ``margin_m`` are queried against the
   hand. No vertex within ``margin_m`` of the hand surface: not ``near``; no vertex inside the
   hand: not ``simulated``; either way the offsets are exactly zero.
2. Only vertices within ``free_radius_m`` of a penetrating vertex move (inverse mass 1); all
   others are pinned where they are (inverse mass 0) and still anchor the constraints they share.
3. ``iterations`` XPBD sweeps over attachment (per-vertex stiffness), stretch, bending, tissue shear
   (neighbouring displacements alike) and collision constraints, ``method`` ``jacobi`` (every constraint at
   once, steps scaled by the vertices' constraint counts, Chebyshev-accelerated; 3x cheaper per sweep here) or
   ``gauss_seidel`` (graph-coloured); collision planes are re-detected every ``detect_every``
   sweeps; or ``direct`` (:mod:`avatar.pbd.direct`): the fixed point those sweeps converge to, by a
   few sparse solves. Positions start from ``warm`` (the previous frame's solution) when given, multipliers
   from zero.
4. Up to ``final_passes`` collision-only passes push any vertex still inside the hand to the hand
   surface plus the clearance, so the residual penetration is bounded by construction.

Stiffnesses are relative to a unit particle mass: XPBD's implicit inertia term ties each free
vertex to its start position with stiffness 1, small next to the attachments (``attach_stiffness``
times the relative stiffness, 360-1440 on the procedural face). The defaults were calibrated on
the synthetic capture synth_a (docs/explanation/pbd.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from avatar.pbd.collision import closest_on_mesh, query_hand
from avatar.pbd.direct import solve_direct
from avatar.pbd.problem import FaceTopology, FrameProblem, PBDConfig
from avatar.threads import single_threaded

#: Plain sweeps before the Chebyshev extrapolation starts.
CHEBYSHEV_DELAY = 10


@dataclass
class FrameResult:
    """One frame's solve: offsets (V, 3) world metres (added to the posed face), face_contact (V,)
    bool, hand_contact (Vh,) bool, and the report numbers (lengths in metres, wall time in seconds)."""

    offsets: torch.Tensor
    face_contact: torch.Tensor
    hand_contact: torch.Tensor
    near: bool
    simulated: bool
    iterations: int = 0
    free_vertices: int = 0
    penetration_max_m: float = 0.0
    penetration_mean_m: float = 0.0
    seconds: float = 0.0

    @property
    def max_offset_m(self) -> float:
        """Largest offset length (metres)."""
        return float(self.offsets.norm(dim=1).max()) if self.offsets.numel() else 0.0


def _iterate(problem: FrameProblem, cfg: PBDConfig) -> None:
    """``cfg.iterations`` sweeps, re-detecting collisions every ``detect_every``. With ``chebyshev_rho``
    > 0 the Jacobi iterates are extrapolated (Wang 2015, Chebyshev semi-iterative acceleration of
    position-based dynamics): ``s_k+1 = omega_k+1 (sweep(s_k) - s_k-1) + s_k-1`` over positions and
    multipliers, ``omega`` from the assumed spectral radius, starting after :data:`CHEBYSHEV_DELAY`
    plain sweeps; collisions are re-projected after each extrapolation."""
    omega, previous = 1.0, None
    for it in range(cfg.iterations):
        if it % cfg.detect_every == 0:
            problem.detect()
        before = [s.clone() for s in problem.state()] if cfg.chebyshev_rho > 0 else None
        problem.sweep()
        if before is None:
            continue
        if it >= CHEBYSHEV_DELAY and previous is not None:
            rho2 = cfg.chebyshev_rho**2
            omega = 2.0 / (2.0 - rho2) if it == CHEBYSHEV_DELAY else 4.0 / (4.0 - rho2 * omega)
            for s, p in zip(problem.state(), previous):
                s.copy_(omega * (s - p) + p)
            problem.collisions.project(problem.x)
        previous = before


def _hand_contact(
    hand: torch.Tensor, face: torch.Tensor, faces: torch.Tensor, face_contact: torch.Tensor, cfg: PBDConfig
) -> torch.Tensor:
    """(Vh,) bool: hand vertices behind, or within ``contact_tolerance_m`` of, the face patch of
    triangles around the contact vertices (face (V, 3), faces (F, 3), face_contact (V,) bool)."""
    out = torch.zeros(hand.shape[0], dtype=torch.bool)
    patch = faces[face_contact[faces].any(dim=1)]
    if patch.numel() == 0:
        return out
    lo, hi = face[face_contact].amin(0) - cfg.max_depth_m, face[face_contact].amax(0) + cfg.max_depth_m
    near = torch.nonzero(((hand >= lo) & (hand <= hi)).all(dim=1)).squeeze(1)
    if near.numel():
        closest, dist, tri = closest_on_mesh(hand[near], face, patch)
        corners = face[patch[tri]]
        normal = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=1)
        behind = ((hand[near] - closest) * normal).sum(1) < 0
        out[near] = (dist < cfg.max_depth_m) & (behind | (dist < cfg.contact_tolerance_m))
    return out


def _penetrating(
    rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, cfg: PBDConfig
) -> tuple[bool, torch.Tensor]:
    """Whether the hand comes within ``margin_m`` of the face (V, 3), and the (S,) face vertices inside it."""
    lo, hi = hand.amin(0) - cfg.margin_m, hand.amax(0) + cfg.margin_m
    cand = torch.nonzero(((rest >= lo) & (rest <= hi)).all(dim=1)).squeeze(1)
    q = query_hand(rest[cand], hand, hand_faces, cfg.max_depth_m)
    return bool((q.distance < cfg.margin_m).any()), cand[q.inside]


def detect_contacts(
    rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, faces: torch.Tensor, cfg: PBDConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Contact flags of the undeformed meshes, without solving: face vertices (V,) inside the hand,
    and hand vertices (Vh,) touching or inside the face around them."""
    _, seeds = _penetrating(rest, hand, hand_faces, cfg)
    face_contact = torch.zeros(rest.shape[0], dtype=torch.bool)
    face_contact[seeds] = True
    return face_contact, _hand_contact(hand, rest, faces, face_contact, cfg)


def solve_frame(
    rest: torch.Tensor,
    hand: torch.Tensor,
    hand_faces: torch.Tensor,
    topology: FaceTopology,
    stiffness: torch.Tensor,
    cfg: PBDConfig,
    warm: torch.Tensor | None = None,
) -> FrameResult:
    """Offsets of one frame (see the module docstring).

    Args:
        rest: (V, 3) posed undeformed face, world metres (float64 recommended).
        hand: (Vh, 3) posed hand, same frame and dtype; hand_faces: (Fh, 3) int64, outward-oriented.
        topology: :meth:`FaceTopology.build` of the face triangles.
        stiffness: (V,) relative attachment stiffness (:mod:`avatar.pbd.stiffness`), >= 0.
        warm: (V, 3) the previous frame's offsets, or None.
    """
    began = time.perf_counter()
    near, seeds = _penetrating(rest, hand, hand_faces, cfg)
    if seeds.numel() == 0:
        return FrameResult(
            torch.zeros_like(rest),
            torch.zeros(rest.shape[0], dtype=torch.bool),
            torch.zeros(hand.shape[0], dtype=torch.bool),
            near=near,
            simulated=False,
        )
    free = torch.cdist(rest, rest[seeds]).amin(dim=1) < cfg.free_radius_m
    start = rest if warm is None else rest + warm
    problem = FrameProblem(rest, hand, hand_faces, topology, stiffness, free, start, cfg)
    iterations = solve_direct(problem) if cfg.method == "direct" else cfg.iterations
    if cfg.method != "direct":
        _iterate(problem, cfg)
    for _ in range(cfg.final_passes + 1):
        q = problem.detect()
        if not bool(q.inside.any()):
            break
        problem.collisions.project(problem.x)
    else:
        q = query_hand(problem.x[problem.free_idx], hand, hand_faces, cfg.max_depth_m)
    face_contact = torch.zeros(rest.shape[0], dtype=torch.bool)
    face_contact[seeds] = True
    face_contact[problem.free_idx[q.inside | (q.distance < cfg.contact_tolerance_m)]] = True
    depth = q.depth
    return FrameResult(
        offsets=problem.x - rest,
        face_contact=face_contact,
        hand_contact=_hand_contact(hand, problem.x, topology.faces, face_contact, cfg),
        near=True,
        simulated=True,
        iterations=iterations,
        free_vertices=int(free.sum()),
        penetration_max_m=float(depth.max()),
        penetration_mean_m=float(depth[face_contact[problem.free_idx]].mean()),
        seconds=time.perf_counter() - began,
    )


def solve_sequence(
    face: torch.Tensor,
    hand: torch.Tensor,
    face_faces: torch.Tensor,
    hand_faces: torch.Tensor,
    stiffness: torch.Tensor,
    cfg: PBDConfig,
) -> list[FrameResult]:
    """Solve every frame on one thread; with ``cfg.warm_start`` each starts from the previous frame's offsets.

    Args: face (T, V, 3) and hand (T, Vh, 3) posed meshes (world metres), their faces, the (V,)
    relative attachment stiffness. Raises ValueError naming the first frame whose meshes are not finite.
    """
    for t in range(face.shape[0]):
        for name, verts in (("face", face[t]), ("hand", hand[t])):
            if not bool(torch.isfinite(verts).all()):
                raise ValueError(
                    f"frame {t}: the posed {name} mesh has non-finite vertices (NaN or inf "
                    f"parameters in this frame); fix or drop the frame's parameters"
                )
    results: list[FrameResult] = []
    with single_threaded():
        topology = FaceTopology.build(face_faces)
        warm = None
        for t in range(face.shape[0]):
            result = solve_frame(face[t], hand[t], hand_faces, topology, stiffness, cfg, warm)
            results.append(result)
            warm = result.offsets if result.simulated and cfg.warm_start else None
    return results
