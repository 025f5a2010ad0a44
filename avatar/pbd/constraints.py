"""XPBD constraint sets and their projections (Macklin et al. 2016, "XPBD").

Every compliant constraint keeps its Lagrange multiplier ``lam`` across iterations and is
projected with ``dlam = -(k C + lam) / (k sum_i w_i |grad_i C|^2 + 1)``, ``dx_i = w_i grad_i C dlam``:
the compliance form ``-(C + alpha lam) / (sum w |grad C|^2 + alpha)`` multiplied through by the
stiffness ``k = 1 / alpha``, so a zero stiffness is a no-op instead of a division by zero. The
solution converges to the minimiser of ``sum_c k_c C_c^2 / 2`` (plus a unit-mass inertia term
about the start positions) whatever the iteration count, which is what makes XPBD stiffness
independent of the number of iterations. Positions ``x`` (V, 3) and inverse masses ``w`` (V,) are
updated in place; ``rows`` selects one colour (constraints sharing no vertex) for a Gauss-Seidel step, or every
constraint for a Jacobi step that adds its corrections to ``out`` instead of ``x``; ``relax``
(a scalar or one value per projected constraint) scales ``dlam``: 1 is plain XPBD; a Jacobi step
uses ``omega / n`` with ``n`` the most constraints any of its vertices takes part in, so the summed
corrections stay stable while multipliers and positions stay consistent (the same fixed point).

Collisions are hard unilateral plane constraints ``n . (x - p) >= 0``, projected without multiplier.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Cotangents are clamped to this magnitude, so a degenerate (zero-area) triangle gives finite weights.
MAX_COT = 20.0


@dataclass
class EdgeSet:
    """Stretch: ``C = |x_i - x_j| - rest``. idx (M, 2), rest (M,), stiffness (M,), lam (M,)."""

    idx: torch.Tensor
    rest: torch.Tensor
    stiffness: torch.Tensor
    lam: torch.Tensor

    def project(
        self,
        x: torch.Tensor,
        w: torch.Tensor,
        rows: torch.Tensor | slice,
        relax: float | torch.Tensor = 1.0,
        out: torch.Tensor | None = None,
    ) -> None:
        i, j = self.idx[rows, 0], self.idx[rows, 1]
        d = x[i] - x[j]
        length = d.norm(dim=1)
        n = d / length.clamp_min(1e-12)[:, None]
        k = self.stiffness[rows]
        wi, wj = w[i], w[j]
        dlam = -relax * (k * (length - self.rest[rows]) + self.lam[rows]) / (k * (wi + wj) + 1.0)
        self.lam[rows] += dlam
        out = x if out is None else out
        out.index_add_(0, i, (wi * dlam)[:, None] * n)
        out.index_add_(0, j, -(wj * dlam)[:, None] * n)

    def residual(self, x: torch.Tensor) -> torch.Tensor:
        """(M,) XPBD residual ``k C + lam`` (zero at the solution)."""
        length = (x[self.idx[:, 0]] - x[self.idx[:, 1]]).norm(dim=1)
        return self.stiffness * (length - self.rest) + self.lam


@dataclass
class LinearSet:
    """Vector constraints linear in the positions: ``C_m = sum_k a_mk x_{idx_mk} - b_m`` (3,).

    idx (M, K), a (M, K), b (M, 3), stiffness (M,), lam (M, 3). Attachment to a target position
    (K = 1, a = 1, b = target) and isometric bending (K = 4, see :func:`bending_set`) are both of
    this form, so one exact projection serves both."""

    idx: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    stiffness: torch.Tensor
    lam: torch.Tensor

    def value(self, x: torch.Tensor, rows: torch.Tensor | slice = slice(None)) -> torch.Tensor:
        """(M, 3) constraint values C."""
        return (self.a[rows, :, None] * x[self.idx[rows]]).sum(1) - self.b[rows]

    def project(
        self,
        x: torch.Tensor,
        w: torch.Tensor,
        rows: torch.Tensor | slice,
        relax: float | torch.Tensor = 1.0,
        out: torch.Tensor | None = None,
    ) -> None:
        idx, a, k = self.idx[rows], self.a[rows], self.stiffness[rows]
        wa = w[idx] * a  # (M, K)
        denom = k * (wa * a).sum(1) + 1.0
        scale = relax[:, None] if isinstance(relax, torch.Tensor) else relax
        dlam = -scale * (k[:, None] * self.value(x, rows) + self.lam[rows]) / denom[:, None]
        self.lam[rows] += dlam
        (x if out is None else out).index_add_(0, idx.reshape(-1), (wa[..., None] * dlam[:, None, :]).reshape(-1, 3))

    def residual(self, x: torch.Tensor) -> torch.Tensor:
        """(M,) norm of the XPBD residual ``k C + lam``."""
        return (self.stiffness[:, None] * self.value(x) + self.lam).norm(dim=1)


def attachment_set(idx: torch.Tensor, target: torch.Tensor, stiffness: torch.Tensor) -> LinearSet:
    """``C = x_i - target_i`` for vertices idx (M,), targets (M, 3), stiffness (M,)."""
    ones = torch.ones_like(stiffness)[:, None]
    return LinearSet(idx[:, None], ones, target, stiffness, torch.zeros_like(target))


def _cot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Cotangent (M,) of the angle between u and v (M, 3), clamped to +-MAX_COT."""
    cross = torch.linalg.cross(u, v, dim=1).norm(dim=1)
    return ((u * v).sum(1) / cross.clamp_min(1e-300)).clamp(-MAX_COT, MAX_COT)


def bending_set(stencils: torch.Tensor, rest: torch.Tensor, stiffness: float) -> LinearSet:
    """Isometric bending (Bergou et al. 2006; Bender et al. 2014) about the rest positions.

    For a stencil ``[x0, x1, x2, x3]`` (edge x0-x1, opposite vertices x2, x3) the weights
    ``K = [cot a1 + cot b1, cot a0 + cot b0, -(cot a0 + cot a1), -(cot b0 + cot b1)]`` (a_i, b_i the
    angles at x_i in the triangles with x2 and x3) make ``sum_k K_k x_k`` the discrete
    mean-curvature vector of the edge: zero for a flat stencil and for rigid or in-plane motion.
    ``C = s sum_k K_k (x_k - rest_k)`` with ``s = sqrt(3 / (A_a + A_b))`` makes ``k |C|^2 / 2`` the
    isometric bending energy, so a bent rest surface (the posed face) is stress-free.

    Args: stencils (B, 4), rest (V, 3) positions, stiffness (scalar for all stencils).
    """
    p = rest[stencils]  # (B, 4, 3)
    e, a2, a3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    b2, b3 = p[:, 2] - p[:, 1], p[:, 3] - p[:, 1]
    cot_a0, cot_a1 = _cot(e, a2), _cot(-e, b2)
    cot_b0, cot_b1 = _cot(e, a3), _cot(-e, b3)
    K = torch.stack([cot_a1 + cot_b1, cot_a0 + cot_b0, -(cot_a0 + cot_a1), -(cot_b0 + cot_b1)], dim=1)
    area = 0.5 * (torch.linalg.cross(e, a2, dim=1).norm(dim=1) + torch.linalg.cross(e, a3, dim=1).norm(dim=1))
    a = K * (3.0 / area.clamp_min(1e-12)).sqrt()[:, None]
    b = (a[..., None] * p).sum(1)
    s = torch.full((stencils.shape[0],), float(stiffness), dtype=rest.dtype, device=rest.device)
    return LinearSet(stencils, a, b, s, torch.zeros_like(b))


@dataclass
class CollisionSet:
    """Hard unilateral planes ``n . (x_i - p) >= 0``: idx (M,), point p (M, 3), unit normal n (M, 3)."""

    idx: torch.Tensor
    point: torch.Tensor
    normal: torch.Tensor

    def project(self, x: torch.Tensor) -> None:
        gap = ((x[self.idx] - self.point) * self.normal).sum(1)
        x[self.idx] += (-gap).clamp_min(0.0)[:, None] * self.normal
