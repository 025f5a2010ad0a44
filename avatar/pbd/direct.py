"""The XPBD fixed point of one frame, solved directly (``method=direct``) instead of by sweeps.

An XPBD step whose multipliers are iterated to convergence lands on the minimiser of

    E(x) = sum_i |x_i - s_i|^2 / 2 + sum_c k_c |C_c(x)|^2 / 2   subject to the collision planes,

``s`` the start positions (the unit-mass inertia term), ``C_c`` the attachment, bending and stretch
constraints of :class:`avatar.pbd.problem.FrameProblem`, and the pinned vertices fixed. Jacobi and
Gauss-Seidel sweeps approach it a ring of vertices per sweep; this module reaches it in a few
sparse solves, with the same constraints and stiffnesses (so the same physical model):

* attachment, bending and inertia are linear in ``x``; stretch ``k (|x_i - x_j| - L)^2 / 2`` is
  ``min_r k |x_i - x_j - L r|^2 / 2`` over unit directions ``r`` (the local/global split of
  projective dynamics, Bouaziz et al. 2014): directions from the current positions (local), then one
  sparse linear solve (global), repeated ``direct_inner`` times;
* the collision planes are an active set of equality constraints (a stiff penalty
  ``COLLISION_STIFFNESS (n . (x - p))^2 / 2``, so a vertex may slide along the hand): after each
  round the vertices inside the hand join it with planes re-detected at their current positions,
  and members whose plane pulls instead of pushes leave it; ``direct_outer`` rounds at most (the
  collision-only passes of :func:`avatar.pbd.solver.solve_frame` follow, as for the sweeps);
* tissue shear coupling (``shear_stiffness``): ``k |d_i - d_j|^2 / 2`` per edge on the displacements
  ``d = x - rest``, the shear of the soft-tissue layer that carries a dent to the skin around it
  (stretch and bending alone, being invariant to rigid motion of an edge, barely do);
* optional tissue-volume preservation (``volume_stiffness`` > 0, :func:`_volume_rows`; off by
  default: it did not help on the synthetic capture, docs/notes/2026-11-pbd-solver-choice.md).

The multipliers are not computed (``problem`` keeps its zero multipliers); positions only.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import splu

from avatar.pbd.collision import query_hand
from avatar.pbd.problem import FrameProblem

#: Penalty stiffness of an active collision plane (relative to a unit particle mass).
COLLISION_STIFFNESS = 1.0e6


def solve_direct(problem: FrameProblem) -> int:
    """Move ``problem.x`` to the XPBD fixed point (see the module docstring); returns the number of
    sparse solves."""
    cfg = problem.cfg
    x = problem.x.detach().cpu().numpy().astype(np.float64)
    free = problem.free_idx.cpu().numpy()
    n = free.shape[0]
    if n == 0:
        return 0
    local = np.full(x.shape[0], -1, dtype=np.int64)
    local[free] = np.arange(n)
    start = x[free].copy()
    rest = problem.rest.detach().cpu().numpy().astype(np.float64)

    # energy rows k |sum_j coef_j x_j - target|^2 / 2: inertia, attachment, bending, then stretch
    rows, cols, vals, weights, targets = [], [], [], [], []
    count = 0

    def add(idx: np.ndarray, coef: np.ndarray, k: np.ndarray, target: np.ndarray) -> tuple[int, int]:
        nonlocal count
        m = idx.shape[0]
        r = np.repeat(np.arange(count, count + m), idx.shape[1])
        rows.append(r)
        cols.append(idx.reshape(-1))
        vals.append(coef.reshape(-1))
        weights.append(k)
        targets.append(target)
        count += m
        return count - m, count

    add(free[:, None], np.ones((n, 1)), np.ones(n), start)
    att = problem.attach
    add(att.idx.cpu().numpy(), att.a.cpu().numpy(), att.stiffness.cpu().numpy(), att.b.cpu().numpy())
    bend = problem.bend
    add(bend.idx.cpu().numpy(), bend.a.cpu().numpy(), bend.stiffness.cpu().numpy(), bend.b.cpu().numpy())
    edges = problem.edges.idx.cpu().numpy()
    length = problem.edges.rest.cpu().numpy()
    if cfg.shear_stiffness > 0:  # tissue shear: neighbours' displacements alike, k |d_i - d_j|^2 / 2 per edge
        add(
            edges,
            np.tile([1.0, -1.0], (edges.shape[0], 1)),
            np.full(edges.shape[0], cfg.shear_stiffness),
            rest[edges[:, 0]] - rest[edges[:, 1]],
        )
    e0, e1 = add(
        edges,
        np.tile([1.0, -1.0], (edges.shape[0], 1)),
        problem.edges.stiffness.cpu().numpy(),
        np.zeros((edges.shape[0], 3)),
    )
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    k = np.concatenate(weights)
    target = np.concatenate(targets)
    # the pinned vertices' terms are constants: moved to the right-hand side
    pinned = local[c] < 0
    G = sp.csr_matrix((v[~pinned], (r[~pinned], local[c[~pinned]])), shape=(count, n))
    P = sp.csr_matrix((v[pinned], (r[pinned], c[pinned])), shape=(count, x.shape[0]))
    pinned_part = P @ x  # (count, 3)
    GtK = (G.T @ sp.diags(k)).tocsr()
    A = (GtK @ G).tocsr()
    A3 = sp.kron(A, sp.identity(3), format="csr")
    vol_rhs = np.zeros((n, 3))
    if cfg.volume_stiffness > 0:
        Gv = _volume_rows(problem, local, n)  # (F, 3n): linearised change of each prism's tissue volume
        A3 = (A3 + cfg.volume_stiffness * (Gv.T @ Gv)).tocsr()
        vol_rhs = vol_rhs + (cfg.volume_stiffness * (Gv.T @ (Gv @ rest[free].reshape(-1)))).reshape(n, 3)

    active = np.zeros(n, dtype=bool)
    point = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    xf = start.copy()
    hand, hand_faces = problem.hand, problem.hand_faces

    def detect(xf: np.ndarray, keep: np.ndarray) -> None:
        q = query_hand(torch.from_numpy(xf).to(hand), hand, hand_faces, cfg.max_depth_m)
        inside = q.inside.cpu().numpy()
        dist = q.distance.cpu().double().numpy()
        closest = q.closest.cpu().double().numpy()
        take = (inside | keep) & (dist > 1e-9)
        sign = np.where(inside, -1.0, 1.0)[:, None]
        nrm = sign * (xf - closest) / np.maximum(dist, 1e-12)[:, None]
        # planes through the closest hand point (plus the clearance), re-detected for every member
        point[take] = closest[take] + cfg.clearance_m * nrm[take]
        normal[take] = nrm[take]
        active[:] = take

    detect(xf, np.zeros(n, dtype=bool))
    solves = 0
    for _ in range(cfg.direct_outer):
        if active.any():
            ids = np.flatnonzero(active)
            nn = normal[ids]
            blocks = COLLISION_STIFFNESS * nn[:, :, None] * nn[:, None, :]  # (m, 3, 3): normal only, slides
            br = (3 * ids[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
            bc = (3 * ids[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
            C = sp.csr_matrix((blocks.reshape(-1), (br.reshape(-1), bc.reshape(-1))), shape=(3 * n, 3 * n))
            crhs = np.zeros((n, 3))
            crhs[ids] = np.einsum("mij,mj->mi", blocks, point[ids])
        else:
            C, crhs = None, np.zeros((n, 3))
        lu = splu((A3 if C is None else A3 + C).tocsc())
        for _ in range(cfg.direct_inner):
            full = x.copy()
            full[free] = xf
            dv = full[edges[:, 0]] - full[edges[:, 1]]
            dirs = dv / np.maximum(np.linalg.norm(dv, axis=1), 1e-12)[:, None]
            target[e0:e1] = length[:, None] * dirs
            rhs = GtK @ (target - pinned_part) + crhs + vol_rhs
            xf = lu.solve(rhs.reshape(-1)).reshape(n, 3)
            solves += 1
        gap = ((xf - point) * normal).sum(1)
        keep = active & (gap < 0)  # still pushed out by its plane
        before = active.copy()
        detect(xf, keep)
        if np.array_equal(before, active):
            break
    x[free] = xf
    problem.x.copy_(torch.from_numpy(x).to(problem.x))
    return solves


def _volume_rows(problem: FrameProblem, local: np.ndarray, n: int) -> sp.csr_matrix:
    """Tissue volume preservation, linearised about the undeformed face: each triangle with a free
    vertex carries a prism of soft tissue, area ``A`` times the mean skin-to-skull distance ``h`` of its
    corners (recovered from the relative stiffness, ``h = reference * s ** (-1 / power)``). Pressing
    the skin in thins the prism; keeping its volume pushes the tissue sideways and bulges the rim.
    Row f: ``(h_f grad A_f + A_f n_i / 3) / A_f`` per corner i (``n_i`` the outward vertex normal),
    so ``k (row . (x - rest))^2 / 2`` penalises the change of mean thickness (metres)."""
    cfg = problem.cfg
    faces = problem.topology_faces
    fa = faces[(local[faces] >= 0).any(axis=1)]
    rest = problem.rest.detach().cpu().numpy().astype(np.float64)
    s = problem.stiffness_rel.detach().cpu().numpy().astype(np.float64)
    power = cfg.stiffness_power if cfg.stiffness_power > 0 else 1.0
    h = np.clip(cfg.reference_thickness_m * np.maximum(s, 1e-12) ** (-1.0 / power), 1e-3, 0.05)
    vn = _vertex_normals(rest, faces)
    p = torch.from_numpy(rest[fa]).requires_grad_(True)
    area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=1).norm(dim=1)
    area.sum().backward()
    assert p.grad is not None  # p is a leaf the area depends on
    grad_a = p.grad.numpy()  # (F, 3, 3)
    a = area.detach().numpy()
    hf = h[fa].mean(1)
    g = (hf[:, None, None] * grad_a + a[:, None, None] * vn[fa] / 3.0) / np.maximum(a, 1e-12)[:, None, None]
    rows = np.repeat(np.arange(fa.shape[0]), 9)
    loc = local[fa]  # (F, 3)
    cols = (3 * loc[:, :, None] + np.arange(3)[None, None, :]).reshape(-1)
    vals = g.reshape(-1)
    keep = np.repeat(loc.reshape(-1) >= 0, 3)
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(fa.shape[0], 3 * n))


def _vertex_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals (outward for outward-oriented faces)."""
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    vn = np.zeros_like(v)
    for c in range(3):
        np.add.at(vn, faces[:, c], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1), 1e-300)[:, None]
