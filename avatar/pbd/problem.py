"""The XPBD system of one frame: the solver's settings (:class:`PBDConfig`), the face's constraint topology
(:class:`FaceTopology`) and the constraints, positions and multipliers of a frame (:class:`FrameProblem`).

:mod:`avatar.pbd.solver` (the sweeps) and :mod:`avatar.pbd.direct` (the fixed point by sparse solves) both
drive a :class:`FrameProblem`; it lives here so that neither imports the other's module for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatar.pbd.collision import HandQuery, query_hand
from avatar.pbd.constraints import CollisionSet, EdgeSet, LinearSet, attachment_set, bending_set
from avatar.pbd.topology import bending_stencils, colour_constraints, unique_edges

METHODS = ("direct", "gauss_seidel", "jacobi")
#: The settings only one family of methods reads: the sweeps (``jacobi``, ``gauss_seidel``) or ``direct``.
SWEEP_ONLY = ("iterations", "relaxation", "chebyshev_rho", "detect_every")
DIRECT_ONLY = ("direct_outer", "direct_inner", "volume_stiffness")


def unused_settings(method: str) -> tuple[str, ...]:
    """The :class:`PBDConfig` fields that solver ``method`` never reads (the other family's); none for an unknown
    method (:class:`PBDConfig` refuses it)."""
    if method not in METHODS:
        return ()
    return SWEEP_ONLY if method == "direct" else DIRECT_ONLY


@dataclass
class PBDConfig:
    """Solver settings (lengths in metres; stiffnesses relative to a unit particle mass). Not frozen:
    the pipeline merges ``stage.pbd.solver`` onto it as a structured config."""

    # direct: the fixed point by sparse solves (the default: 2-3x faster than 300 Jacobi sweeps, converged). jacobi (all
    # constraints at once) and gauss_seidel (graph-coloured) sweep the same model to it: kept as the reference the
    # direct solve is tested against (3000 sweeps), and for the XPBD-style early stop
    # (docs/notes/2026-11-pbd-solver-choice.md)
    method: str = "direct"
    iterations: int = 300  # jacobi / gauss_seidel: sweeps per contact frame
    relaxation: float = 1.0  # scales every multiplier step (1: plain XPBD)
    chebyshev_rho: float = 0.999  # Chebyshev acceleration of the Jacobi sweeps (assumed spectral radius; 0: off)
    detect_every: int = 100  # sweeps between collision re-detections
    final_passes: int = 4  # collision-only passes after the sweeps (residual penetration)
    direct_outer: int = 6  # direct: active-set rounds of collision planes
    direct_inner: int = 10  # direct: local/global solves per round
    # direct only: tissue-volume preservation. Off: 10 gave 50.1 % and 100 gave 78 % of the zero-offset error against
    # 46.7 % without; kept as the measured alternative to the shear term (docs/notes/2026-11-pbd-solver-choice.md)
    volume_stiffness: float = 0.0
    shear_stiffness: float = 350.0  # tissue shear: neighbouring displacements alike (docs/explanation/pbd.md)
    # start each frame from the previous one's offsets. Off: at draft's frame spacing it cost accuracy (48 % -> 69 % of
    # the zero-offset error); kept for densely sampled video, where it may pay off
    # (docs/notes/2026-11-pbd-solver-choice.md)
    warm_start: bool = False
    margin_m: float = 0.01  # hand farther than this from the face: frame not simulated (zero offsets)
    free_radius_m: float = 0.03  # vertices this close to a penetrating vertex move; the rest are pinned
    clearance_m: float = 0.0002  # vertices are pushed this far outside the hand surface
    max_depth_m: float = 0.02  # deepest a face vertex can lie inside the hand (a hand is ~3 cm thick)
    contact_tolerance_m: float = 0.001  # contact flags: within this distance of the other surface
    edge_stiffness: float = 10.0  # stretch
    bend_stiffness: float = 3.0e-4  # isometric bending between adjacent triangles
    attach_stiffness: float = 720.0  # pull back to the undeformed position, for tissue of reference thickness
    reference_thickness_m: float = 0.01  # skin-to-skull distance of relative stiffness 1
    stiffness_power: float = 2.0  # stiffness ~ (reference / thickness) ** power: thin tissue over bone is stiff

    def __post_init__(self) -> None:
        problems = []
        if self.method not in METHODS:
            problems.append(f"method={self.method!r}: choose one of {METHODS}")
        if not 0.0 <= self.chebyshev_rho < 1.0 or (self.chebyshev_rho > 0 and self.method == "gauss_seidel"):
            problems.append(
                f"chebyshev_rho={self.chebyshev_rho}: must lie in [0, 1), and be 0 unless method=jacobi "
                f"(it diverges on Gauss-Seidel)"
            )
        if not 0.0 < self.relaxation <= 2.0:
            problems.append(f"relaxation={self.relaxation}: must lie in (0, 2] (larger steps diverge)")
        if self.iterations < 0 or self.detect_every < 1 or self.final_passes < 0:
            problems.append("iterations and final_passes must be >= 0, detect_every >= 1")
        if self.direct_outer < 1 or self.direct_inner < 1:
            problems.append(f"direct_outer={self.direct_outer}, direct_inner={self.direct_inner}: must be >= 1")
        if self.volume_stiffness > 0 and self.method != "direct":
            problems.append(f"volume_stiffness={self.volume_stiffness}: only method=direct has the volume term")
        lengths = (
            "margin_m",
            "free_radius_m",
            "clearance_m",
            "max_depth_m",
            "contact_tolerance_m",
            "reference_thickness_m",
        )
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


class FrameProblem:
    """The XPBD system of one frame (see the module docstring); :func:`solve_frame` drives it.

    Args:
        rest: (V, 3) posed undeformed face; hand: (Vh, 3) posed hand; hand_faces: (Fh, 3).
        topology: the face's :class:`FaceTopology`; stiffness: (V,) relative attachment stiffness.
        free: (V,) bool, the vertices that may move; start: (V, 3) initial positions (warm start).
    """

    def __init__(
        self,
        rest: torch.Tensor,
        hand: torch.Tensor,
        hand_faces: torch.Tensor,
        topology: FaceTopology,
        stiffness: torch.Tensor,
        free: torch.Tensor,
        start: torch.Tensor,
        cfg: PBDConfig,
    ) -> None:
        self.rest, self.hand, self.hand_faces, self.cfg = rest, hand, hand_faces, cfg
        self.topology_faces = topology.faces.cpu().numpy()
        self.stiffness_rel = stiffness
        self.x = torch.where(free[:, None], start, rest).clone()
        self.w = free.to(rest.dtype)
        self.free_idx = torch.nonzero(free).squeeze(1)
        self.attach = attachment_set(
            self.free_idx, rest[self.free_idx], cfg.attach_stiffness * stiffness[self.free_idx].to(rest.dtype)
        )
        active_e = free[topology.edges].any(dim=1)
        edges = topology.edges[active_e]
        self.edges = EdgeSet(
            edges,
            (rest[edges[:, 0]] - rest[edges[:, 1]]).norm(dim=1),
            torch.full((edges.shape[0],), cfg.edge_stiffness, dtype=rest.dtype),
            rest.new_zeros(edges.shape[0]),
        )
        self.edge_colours = _active(topology.edge_colours, active_e)
        active_b = free[topology.stencils].any(dim=1)
        self.bend = bending_set(topology.stencils[active_b], rest, cfg.bend_stiffness)
        self.bend_colours = _active(topology.bend_colours, active_b)
        # tissue shear: k |d_i - d_j|^2 / 2 on the displacements d = x - rest of every active edge
        self.shear = LinearSet(
            edges,
            torch.tensor([1.0, -1.0], dtype=rest.dtype).repeat(edges.shape[0], 1),
            rest[edges[:, 0]] - rest[edges[:, 1]],
            torch.full((edges.shape[0],), cfg.shear_stiffness, dtype=rest.dtype),
            rest.new_zeros(edges.shape[0], 3),
        )
        self.collisions = CollisionSet(self.free_idx[:0], rest[:0], rest[:0])
        # Jacobi: each constraint's step is divided by the most constraints one of its vertices takes part in
        count = self.w.clone()  # one attachment per free vertex
        shear_idx = [edges.reshape(-1)] if cfg.shear_stiffness > 0 else []
        for idx in [edges.reshape(-1), self.bend.idx.reshape(-1)] + shear_idx:
            count.index_add_(0, idx, torch.ones(idx.shape[0], dtype=rest.dtype))
        self.jacobi_relax = [
            cfg.relaxation / count[c.idx].amax(dim=1).clamp_min(1.0)
            for c in (self.attach, self.edges, self.bend, self.shear)
        ]

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
            sets: tuple[LinearSet | EdgeSet, ...] = (self.attach, self.edges, self.bend, self.shear)
            for constraints, jacobi_relax in zip(sets, self.jacobi_relax):
                constraints.project(self.x, self.w, slice(None), jacobi_relax, out=dx)
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
        parts = (
            self.attach.residual(self.x),
            self.edges.residual(self.x),
            self.bend.residual(self.x),
            self.shear.residual(self.x),
        )
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
