"""XPBD contact solve of the face against the kinematic hand, one frame at a time.

Per frame (:func:`solve_frame`), on the posed, undeformed face ``rest`` (V, 3):

1. Face vertices inside the hand's bounding box grown by ``margin_m`` are queried against the
   hand. No vertex within ``margin_m`` of the hand surface: not ``near``; no vertex inside the
   hand: not ``simulated``; either way the offsets are exactly zero.
2. Only vertices within ``free_radius_m`` of a penetrating vertex move (inverse mass 1); all
   others are pinned where they are (inverse mass 0) and still anchor the constraints they share.
3. ``iterations`` XPBD sweeps over attachment (per-vertex stiffness), stretch, bending, tissue shear
   (neighbouring displacements alike) and collision constraints, ``method`` ``jacobi`` (every constraint at once, steps scaled by the
   vertices' constraint counts, Chebyshev-accelerated; the default: 3x cheaper per sweep here) or
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

from avatar.pbd.collision import HandQuery, closest_on_mesh, query_hand
from avatar.pbd.direct import solve_direct
from avatar.pbd.constraints import CollisionSet, EdgeSet, LinearSet, attachment_set, bending_set
from avatar.pbd.topology import bending_stencils, colour_constraints, unique_edges
from avatar.threads import single_threaded


METHODS = ("direct", "gauss_seidel", "jacobi")
#: Plain sweeps before the Chebyshev extrapolation starts.
CHEBYSHEV_DELAY = 10


@dataclass
class PBDConfig:
    """Solver settings (lengths in metres; stiffnesses relative to a unit particle mass). Not frozen:
    the pipeline merges ``stage.pbd.solver`` onto it as a structured config."""

    method: str = "direct"
    iterations: int = 300
    relaxation: float = 1.0
    chebyshev_rho: float = 0.999
    detect_every: int = 100
    final_passes: int = 4
    direct_outer: int = 6  # method=direct: active-set rounds of collision planes
    direct_inner: int = 10  # method=direct: local/global solves per round
    volume_stiffness: float = 0.0  # method=direct: tissue-volume preservation (0: off; it did not help)
    shear_stiffness: float = 350.0  # tissue shear: couples neighbouring displacements (0: off)
    warm_start: bool = False
    margin_m: float = 0.01
    free_radius_m: float = 0.03
    clearance_m: float = 0.0002
    max_depth_m: float = 0.02
    contact_tolerance_m: float = 0.001
    edge_stiffness: float = 10.0
    bend_stiffness: float = 3.0e-4
    attach_stiffness: float = 720.0
    reference_thickness_m: float = 0.01
    stiffness_power: float = 2.0

    def __post_init__(self) -> None:
        problems = []
        if self.method not in METHODS:
            problems.append(f"method={self.method!r}: choose one of {METHODS}")
        if not 0.0 <= self.chebyshev_rho < 1.0 or (self.chebyshev_rho > 0 and self.method == "gauss_seidel"):
            problems.append(f"chebyshev_rho={self.chebyshev_rho}: must lie in [0, 1), and be 0 unless method=jacobi "
                            f"(it diverges on Gauss-Seidel)")
        if not 0.0 < self.relaxation <= 2.0:
            problems.append(f"relaxation={self.relaxation}: must lie in (0, 2] (larger steps diverge)")
        if self.iterations < 0 or self.detect_every < 1 or self.final_passes < 0:
            problems.append("iterations and final_passes must be >= 0, detect_every >= 1")
        if self.direct_outer < 1 or self.direct_inner < 1:
            problems.append(f"direct_outer={self.direct_outer}, direct_inner={self.direct_inner}: must be >= 1")
        if self.volume_stiffness > 0 and self.method != "direct":
            problems.append(f"volume_stiffness={self.volume_stiffness}: only method=direct has the volume term")
        lengths = ("margin_m", "free_radius_m", "clearance_m", "max_depth_m", "contact_tolerance_m",
                   "reference_thickness_m")
        stiffnesses = ("edge_stiffness", "bend_stiffness", "attach_stiffness", "volume_stiffness", "shear_stiffness")
        problems += [f"{k}={getattr(self, k)}: must be > 0" for k in lengths if not getattr(self, k) > 0]
        problems += [f"{k}={getattr(self, k)}: must be >= 0" for k in stiffnesses if not getattr(self, k) >= 0]
        if problems:
            raise ValueError("PBDConfig: " + "; ".join(problems))


@dataclass(frozen=True)
class FaceTopology:
    """The face mesh's constraint topology, built once per mesh: faces (F, 3), edges (E, 2),
    bending stencils (B, 4) and their Gauss-Seidel colours (row indices per colour)."""

    faces: torch.Tensor
    edges: torch.Tensor
    stencils: torch.Tensor
    edge_colours: list[torch.Tensor]
    bend_colours: list[torch.Tensor]

    @classmethod
    def build(cls, faces: torch.Tensor) -> FaceTopology:
        edges, stencils = unique_edges(faces), bending_stencils(faces)
        return cls(faces, edges, stencils, colour_constraints(edges), colour_constraints(stencils))


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


class FrameProblem:
    """The XPBD system of one frame (see the module docstring); :func:`solve_frame` drives it.

    Args:
        rest: (V, 3) posed undeformed face; hand: (Vh, 3) posed hand; hand_faces: (Fh, 3).
        topology: the face's :class:`FaceTopology`; stiffness: (V,) relative attachment stiffness.
        free: (V,) bool, the vertices that may move; start: (V, 3) initial positions (warm start).
    """

    def __init__(self, rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, topology: FaceTopology,
                 stiffness: torch.Tensor, free: torch.Tensor, start: torch.Tensor, cfg: PBDConfig) -> None:
        self.rest, self.hand, self.hand_faces, self.cfg = rest, hand, hand_faces, cfg
        self.topology_faces = topology.faces.cpu().numpy()
        self.stiffness_rel = stiffness
        self.x = torch.where(free[:, None], start, rest).clone()
        self.w = free.to(rest.dtype)
        self.free_idx = torch.nonzero(free).squeeze(1)
        self.attach = attachment_set(self.free_idx, rest[self.free_idx],
                                     cfg.attach_stiffness * stiffness[self.free_idx].to(rest.dtype))
        active_e = free[topology.edges].any(dim=1)
        edges = topology.edges[active_e]
        self.edges = EdgeSet(edges, (rest[edges[:, 0]] - rest[edges[:, 1]]).norm(dim=1),
                             torch.full((edges.shape[0],), cfg.edge_stiffness, dtype=rest.dtype),
                             rest.new_zeros(edges.shape[0]))
        self.edge_colours = _active(topology.edge_colours, active_e)
        active_b = free[topology.stencils].any(dim=1)
        self.bend = bending_set(topology.stencils[active_b], rest, cfg.bend_stiffness)
        self.bend_colours = _active(topology.bend_colours, active_b)
        # tissue shear: k |d_i - d_j|^2 / 2 on the displacements d = x - rest of every active edge
        self.shear = LinearSet(edges, torch.tensor([1.0, -1.0], dtype=rest.dtype).repeat(edges.shape[0], 1),
                               rest[edges[:, 0]] - rest[edges[:, 1]],
                               torch.full((edges.shape[0],), cfg.shear_stiffness, dtype=rest.dtype),
                               rest.new_zeros(edges.shape[0], 3))
        self.collisions = CollisionSet(self.free_idx[:0], rest[:0], rest[:0])
        # Jacobi: each constraint's step is divided by the most constraints one of its vertices takes part in
        count = self.w.clone()  # one attachment per free vertex
        shear_idx = [edges.reshape(-1)] if cfg.shear_stiffness > 0 else []
        for idx in [edges.reshape(-1), self.bend.idx.reshape(-1)] + shear_idx:
            count.index_add_(0, idx, torch.ones(idx.shape[0], dtype=rest.dtype))
        self.jacobi_relax = [cfg.relaxation / count[c.idx].amax(dim=1).clamp_min(1.0)
                             for c in (self.attach, self.edges, self.bend, self.shear)]

    def detect(self) -> HandQuery:
        """Refresh the collision planes from the free vertices' current positions."""
        q = query_hand(self.x[self.free_idx], self.hand, self.hand_faces, self.cfg.max_depth_m)
        self.collisions = collision_planes(self.x[self.free_idx], q, self.free_idx, self.cfg)
        return q

    def sweep(self) -> None:
        """One sweep over attachments, stretch and bending (Gauss-Seidel: colour by colour; Jacobi: all
        at once from the same positions), then the collision planes."""
        if self.cfg.method == "jacobi":
            dx = torch.zeros_like(self.x)
            for constraints, relax in zip((self.attach, self.edges, self.bend, self.shear), self.jacobi_relax):
                constraints.project(self.x, self.w, slice(None), relax, out=dx)
            self.x += dx
        else:
            relax = self.cfg.relaxation
            self.attach.project(self.x, self.w, slice(None), relax)
            for rows in self.edge_colours:
                self.edges.project(self.x, self.w, rows, relax)
            for rows in self.bend_colours:
                self.bend.project(self.x, self.w, rows, relax)
            if self.cfg.shear_stiffness > 0:
                for rows in self.edge_colours:
                    self.shear.project(self.x, self.w, rows, relax)
        self.collisions.project(self.x)

    def state(self) -> list[torch.Tensor]:
        """The solver state: positions and every multiplier (updated in place by the sweeps)."""
        return [self.x, self.attach.lam, self.edges.lam, self.bend.lam, self.shear.lam]

    def residual(self) -> float:
        """Largest XPBD residual ``|k C + lam|`` over the compliant constraints (zero at convergence)."""
        parts = (self.attach.residual(self.x), self.edges.residual(self.x), self.bend.residual(self.x),
                 self.shear.residual(self.x))
        return float(torch.cat(parts).abs().max())


def _active(colours: list[torch.Tensor], active: torch.Tensor) -> list[torch.Tensor]:
    """Each colour's rows among the active constraints (numbered as in ``active.nonzero()``); empty
    colours dropped."""
    new_index = torch.cumsum(active.long(), 0) - 1
    return [new_index[r] for r in (rows[active[rows]] for rows in colours) if r.numel()]


def collision_planes(points: torch.Tensor, q: HandQuery, idx: torch.Tensor, cfg: PBDConfig) -> CollisionSet:
    """Planes for points (N, 3) (vertex ids idx (N,)) inside the hand or closer to it than the
    clearance plus the contact tolerance: through the closest hand point moved out by the clearance,
    normal pointing out of the hand (the exit direction from inside; away from the hand outside)."""
    take = (q.inside | (q.distance < cfg.clearance_m + cfg.contact_tolerance_m)) & (q.distance > 1e-9)
    sign = torch.where(q.inside, -1.0, 1.0).to(points.dtype)[:, None]
    normal = sign * (points - q.closest) / q.distance.clamp_min(1e-12)[:, None]
    return CollisionSet(idx[take], (q.closest + cfg.clearance_m * normal)[take], normal[take])


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
            rho2 = cfg.chebyshev_rho ** 2
            omega = 2.0 / (2.0 - rho2) if it == CHEBYSHEV_DELAY else 4.0 / (4.0 - rho2 * omega)
            for s, p in zip(problem.state(), previous):
                s.copy_(omega * (s - p) + p)
            problem.collisions.project(problem.x)
        previous = before


def _hand_contact(hand: torch.Tensor, face: torch.Tensor, faces: torch.Tensor, face_contact: torch.Tensor,
                  cfg: PBDConfig) -> torch.Tensor:
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


def _penetrating(rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, cfg: PBDConfig
                 ) -> tuple[bool, torch.Tensor]:
    """Whether the hand comes within ``margin_m`` of the face (V, 3), and the (S,) face vertices inside it."""
    lo, hi = hand.amin(0) - cfg.margin_m, hand.amax(0) + cfg.margin_m
    cand = torch.nonzero(((rest >= lo) & (rest <= hi)).all(dim=1)).squeeze(1)
    q = query_hand(rest[cand], hand, hand_faces, cfg.max_depth_m)
    return bool((q.distance < cfg.margin_m).any()), cand[q.inside]


def detect_contacts(rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, faces: torch.Tensor,
                    cfg: PBDConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Contact flags of the undeformed meshes, without solving: face vertices (V,) inside the hand,
    and hand vertices (Vh,) touching or inside the face around them."""
    _, seeds = _penetrating(rest, hand, hand_faces, cfg)
    face_contact = torch.zeros(rest.shape[0], dtype=torch.bool)
    face_contact[seeds] = True
    return face_contact, _hand_contact(hand, rest, faces, face_contact, cfg)


def solve_frame(rest: torch.Tensor, hand: torch.Tensor, hand_faces: torch.Tensor, topology: FaceTopology,
                stiffness: torch.Tensor, cfg: PBDConfig, warm: torch.Tensor | None = None) -> FrameResult:
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
        return FrameResult(torch.zeros_like(rest), torch.zeros(rest.shape[0], dtype=torch.bool),
                           torch.zeros(hand.shape[0], dtype=torch.bool), near=near, simulated=False)
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
        offsets=problem.x - rest, face_contact=face_contact,
        hand_contact=_hand_contact(hand, problem.x, topology.faces, face_contact, cfg),
        near=True, simulated=True, iterations=iterations, free_vertices=int(free.sum()),
        penetration_max_m=float(depth.max()), penetration_mean_m=float(depth[face_contact[problem.free_idx]].mean()),
        seconds=time.perf_counter() - began,
    )


def solve_sequence(face: torch.Tensor, hand: torch.Tensor, face_faces: torch.Tensor, hand_faces: torch.Tensor,
                   stiffness: torch.Tensor, cfg: PBDConfig) -> list[FrameResult]:
    """Solve every frame on one thread; with ``cfg.warm_start`` each starts from the previous frame's offsets.

    Args: face (T, V, 3) and hand (T, Vh, 3) posed meshes (world metres), their faces, the (V,)
    relative attachment stiffness. Raises ValueError naming the first frame whose meshes are not finite.
    """
    for t in range(face.shape[0]):
        for name, verts in (("face", face[t]), ("hand", hand[t])):
            if not bool(torch.isfinite(verts).all()):
                raise ValueError(f"frame {t}: the posed {name} mesh has non-finite vertices (NaN or inf "
                                 f"parameters in this frame); fix or drop the frame's parameters")
    results: list[FrameResult] = []
    with single_threaded():
        topology = FaceTopology.build(face_faces)
        warm = None
        for t in range(face.shape[0]):
            result = solve_frame(face[t], hand[t], hand_faces, topology, stiffness, cfg, warm)
            results.append(result)
            warm = result.offsets if result.simulated and cfg.warm_start else None
    return results
