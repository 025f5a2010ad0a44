"""3DGS adaptive density control for mesh-embedded Gaussians (SplattingAvatar).

Schedule and thresholds follow ``configs/splatting_avatar.yaml`` and ``model/splatting_avatar_optim.py``
(``adaptive_density_control``, ``densify_and_prune``) of ``initialneil/SplattingAvatar``: view-space
positional gradients are accumulated while ``step <= densify_until``; every ``densify_interval`` steps
from ``densify_from`` on, Gaussians whose mean gradient reaches ``grad_threshold`` (2e-4, NDC units) are

- cloned when their largest canonical scale is at most ``percent_dense * extent`` (a copy in place:
  same triangle, barycentrics and displacement);
- split otherwise: two children with scales divided by 1.6, offsets drawn from the parent's canonical
  Gaussian (``N(0, diag(s^2))`` rotated by it) and written as barycentric and displacement steps on
  the parent's canonical triangle (least squares in the triangle's plane, the rest along the
  interpolated normal); children start on the parent's triangle and then walk
  (:mod:`avatar.representations.embedded.walking`), so they always end on a valid triangle. The public code projects
  split children onto the mesh with its Phong-surface solver instead.

Then Gaussians are pruned when their opacity is below ``min_opacity`` (0.005) or any parameter is
non-finite, and, once past the first opacity reset, when their screen radius exceeded
``max_screen_radius`` pixels (public ``size_threshold`` 20) or their largest canonical scale exceeds
``0.1 * extent``. If pruning would empty the model the most opaque Gaussian stays. Every
``opacity_reset_interval`` steps in the window opacities are capped at 0.01 and their Adam moments
zeroed. ``max_gaussians`` caps growth (150 000, the public ``optim.max_n_gauss``). The public code
selects split candidates by their canonical scale and clone candidates by their posed one; here both
by the canonical scale, which does not depend on the frame that happened to be drawn.

Rows are rebuilt by one gather (:func:`_gather_rows`): survivors in their order, then clones, then
split children; every parameter's Adam moments are gathered with them (zero for new rows).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from avatar.representations.bound.gaussians import inverse_sigmoid
from avatar.representations.embedded.embedding import PARAM_NAMES, EmbeddedGaussians, barycentric_blend
from avatar.representations.embedded.walking import full_barycentric

SPLIT_CHILDREN = 2
SPLIT_SCALE_DIVISOR = 0.8 * SPLIT_CHILDREN  # 3DGS: children's scales are the parent's / (0.8 N)


@dataclass(frozen=True)
class EmbeddedDensityConfig:
    """Density control schedule (optimizer steps, 1-based; ``densify_until = 0`` disables it) and thresholds."""

    densify_from: int
    densify_until: int
    densify_interval: int
    opacity_reset_interval: int
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    reset_opacity: float = 0.01
    max_screen_radius: float = 20.0
    max_world_fraction: float = 0.1
    max_gaussians: int = 150_000

    @property
    def enabled(self) -> bool:
        return self.densify_until > 0


class EmbeddedDensityController:
    """Accumulates per-Gaussian statistics between densification steps and applies the schedule.

    Attributes:
        grad_sum: (N,) summed NDC positional gradient norms; ``count`` (N,) views that saw each Gaussian;
        max_radii: (N,) largest screen radius (px) seen; ``generator`` draws the split offsets.
    """

    def __init__(
        self, cfg: EmbeddedDensityConfig, num_gaussians: int, seed: int = 0, device: torch.device | None = None
    ) -> None:
        self.cfg = cfg
        self.generator = torch.Generator(device=device or "cpu").manual_seed(seed)
        self._reset_stats(num_gaussians, device)

    def _reset_stats(self, n: int, device: torch.device | None) -> None:
        self.grad_sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    def state(self) -> dict[str, Tensor]:
        """Everything needed to resume bit for bit."""
        return {
            "grad_sum": self.grad_sum,
            "count": self.count,
            "max_radii": self.max_radii,
            "generator": self.generator.get_state(),
        }

    def load_state(self, state: dict[str, Tensor]) -> None:
        self.grad_sum, self.count, self.max_radii = state["grad_sum"], state["count"], state["max_radii"]
        self.generator.set_state(state["generator"])

    def accumulate(self, step: int, grad2d_px: Tensor, radii: Tensor, image_size: int) -> None:
        """Add one view's (N,) pixel-space positional gradient norms and (N,) radii (0: not visible).

        Pixel gradients become NDC ones (times ``image_size / 2``) so 2e-4 holds at any resolution.
        """
        if not (self.cfg.enabled and step <= self.cfg.densify_until):
            return
        visible = radii > 0
        ndc = grad2d_px.detach().float() * (image_size / 2)
        self.grad_sum += torch.where(visible, ndc, torch.zeros_like(ndc))
        self.count += visible.float()
        self.max_radii = torch.maximum(self.max_radii, radii.detach().float())

    def step(
        self, step: int, model: EmbeddedGaussians, optimizer: torch.optim.Optimizer, extent: float
    ) -> dict[str, int]:
        """Apply the schedule after optimizer step ``step``; counts of what changed."""
        c = self.cfg
        done = {"cloned": 0, "split": 0, "pruned": 0, "walked": 0, "reset": 0}
        if not (c.enabled and step <= c.densify_until):
            return done
        if step >= c.densify_from and step % c.densify_interval == 0:
            done.update(self._densify_and_prune(step, model, optimizer, extent))
        if step % c.opacity_reset_interval == 0:
            reset_opacity(model, optimizer, c.reset_opacity)
            done["reset"] = model.num_gaussians
        return done

    def _densify_and_prune(
        self, step: int, model: EmbeddedGaussians, optimizer: torch.optim.Optimizer, extent: float
    ) -> dict[str, int]:
        c = self.cfg
        grads = self.grad_sum / self.count.clamp_min(1)
        canonical_max = torch.exp(model.log_scales.detach()).amax(-1)
        hot = grads >= c.grad_threshold
        big = canonical_max > c.percent_dense * extent
        room = max(c.max_gaussians - model.num_gaussians, 0)
        clone_idx = torch.nonzero(hot & ~big).flatten()[:room]
        split_idx = torch.nonzero(hot & big).flatten()[: max(room - len(clone_idx), 0) // (SPLIT_CHILDREN - 1)]
        prune = prunable(model, c.min_opacity)
        if step > c.opacity_reset_interval:
            prune |= (self.max_radii > c.max_screen_radius) | (canonical_max > c.max_world_fraction * extent)
        prune = _keep_one(model, prune)
        removed = prune.clone()
        removed[split_idx] = True
        survivors = torch.nonzero(~removed).flatten()
        clones = clone_idx[~prune[clone_idx]]
        parents = split_idx[~prune[split_idx]].repeat(SPLIT_CHILDREN)
        children = split_children(model, parents, self.generator)
        rows = torch.cat([survivors, clones, parents])
        fresh = torch.zeros(len(rows), dtype=torch.bool, device=rows.device)
        fresh[len(survivors) :] = True
        overrides = {name: (len(survivors) + len(clones), value) for name, value in children.items()}
        before = model.num_gaussians
        _gather_rows(model, optimizer, rows, fresh, overrides)
        walked = model.walk()
        _zero_moments(optimizer, model.barycentric, walked)
        self._reset_stats(model.num_gaussians, self.grad_sum.device)
        return {
            "cloned": len(clones),
            "split": len(parents) // SPLIT_CHILDREN,
            "pruned": int(prune.sum()),
            "walked": int(walked.sum()),
            "total_before": before,
            "total_after": model.num_gaussians,
        }


def prunable(model: EmbeddedGaussians, min_opacity: float) -> Tensor:
    """(N,) bool: opacity below ``min_opacity`` or any parameter non-finite."""
    n = model.num_gaussians
    bad = model.opacities().detach() < min_opacity
    for name in PARAM_NAMES:
        bad |= ~torch.isfinite(getattr(model, name).detach().reshape(n, -1)).all(-1)
    return bad


def _keep_one(model: EmbeddedGaussians, prune: Tensor) -> Tensor:
    """``prune`` with the most opaque finite Gaussian spared when it would remove them all."""
    if model.num_gaussians == 0 or not bool(prune.all()):
        return prune
    score = torch.nan_to_num(model.opacity_logits.detach(), nan=-torch.inf)
    spared = prune.clone()
    spared[int(score.argmax())] = False
    return spared


def split_children(model: EmbeddedGaussians, parents: Tensor, generator: torch.Generator) -> dict[str, Tensor]:
    """Barycentrics, displacements and log-scales of children of ``parents`` (M,) (one row per child).

    Offsets ~ ``q N(0, diag(s^2))`` in the canonical frame (``q``, ``s`` the parent's canonical rotation
    and scales) become steps ``(du, dv)`` on the canonical triangle (least squares in its plane) and
    ``dd`` along the interpolated canonical normal.
    """
    mesh = model.mesh
    scales = torch.exp(model.log_scales.detach()[parents])
    noise = torch.randn(scales.shape, generator=generator, dtype=scales.dtype, device=scales.device)
    offsets = _rotate(F.normalize(model.quats.detach()[parents], dim=-1), noise * scales)
    corners = mesh.faces[model.triangle[parents]]
    p0, p1, p2 = (mesh.vertices[corners[:, c]] for c in range(3))
    edges = torch.stack([p0 - p2, p1 - p2], dim=-1)  # d(position)/d(u, v): (M, 3, 2)
    gram = edges.transpose(-1, -2) @ edges
    ridge = 1e-12 * gram.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)
    gram = gram + ridge[:, None, None] * torch.eye(2, dtype=gram.dtype, device=gram.device)
    step_uv = torch.linalg.solve(gram, edges.transpose(-1, -2) @ offsets[..., None])[..., 0]
    bary = full_barycentric(model.barycentric.detach()[parents])
    normal = F.normalize(barycentric_blend(mesh.normals, corners, bary), dim=-1, eps=1e-30)
    return {
        "barycentric": model.barycentric.detach()[parents] + step_uv,
        "displacement": model.displacement.detach()[parents] + (offsets * normal).sum(-1),
        "log_scales": torch.log(scales / SPLIT_SCALE_DIVISOR),
    }


def _rotate(q: Tensor, v: Tensor) -> Tensor:
    """Vectors ``v`` (M, 3) rotated by unit quaternions ``q`` (M, 4, w x y z)."""
    w, r = q[:, :1], q[:, 1:]
    uv = torch.linalg.cross(r, v)
    return v + 2.0 * (w * uv + torch.linalg.cross(r, uv))


def _param_state(optimizer: torch.optim.Optimizer, param: nn.Parameter) -> dict | None:
    return optimizer.state.get(param)


def _swap_param(optimizer: torch.optim.Optimizer, old: nn.Parameter, new: nn.Parameter, state: dict | None) -> None:
    """Put ``new`` in ``old``'s place in the optimizer, with ``state`` as its Adam state."""
    for group in optimizer.param_groups:
        group["params"] = [new if p is old else p for p in group["params"]]
    optimizer.state.pop(old, None)
    if state is not None:
        optimizer.state[new] = state


def _gather_rows(
    model: EmbeddedGaussians,
    optimizer: torch.optim.Optimizer,
    rows: Tensor,
    fresh: Tensor,
    overrides: dict[str, tuple[int, Tensor]],
) -> None:
    """Rebuild every per-Gaussian tensor as ``old[rows]``; ``overrides[name] = (start, values)`` replace the
    rows from ``start`` on; Adam moments follow the rows and are zero where ``fresh`` (M,) is true."""
    for name in PARAM_NAMES:
        old = getattr(model, name)
        value = old.detach()[rows]
        if name in overrides:
            start, replacement = overrides[name]
            value[start : start + len(replacement)] = replacement.to(value.dtype)
        new = nn.Parameter(value)
        state = _param_state(optimizer, old)
        if state is not None:
            mask = (~fresh).reshape(-1, *([1] * (value.dim() - 1)))
            state = {
                key: (moment[rows] * mask if torch.is_tensor(moment) and moment.dim() > 0 else moment)
                for key, moment in state.items()
            }
        _swap_param(optimizer, old, new, state)
        setattr(model, name, new)
    model.triangle = model.triangle[rows]
    model.part = model.part[rows]


def _zero_moments(optimizer: torch.optim.Optimizer, param: nn.Parameter, rows: Tensor) -> None:
    """Zero the Adam moments of ``param`` at the (N,) bool ``rows``."""
    state = _param_state(optimizer, param)
    if not state or not bool(rows.any()):
        return
    for moment in state.values():
        if torch.is_tensor(moment) and moment.dim() > 0:
            moment[rows] = 0.0


def reset_opacity(model: EmbeddedGaussians, optimizer: torch.optim.Optimizer, ceiling: float) -> None:
    """Cap every opacity at ``ceiling`` and zero its Adam moments (3DGS opacity reset)."""
    old = model.opacity_logits
    cap = inverse_sigmoid(torch.tensor(ceiling, dtype=old.dtype, device=old.device))
    new = nn.Parameter(torch.minimum(old.detach(), cap))
    state = _param_state(optimizer, old)
    if state is not None:
        state = {k: (torch.zeros_like(v) if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in state.items()}
    _swap_param(optimizer, old, new, state)
    model.opacity_logits = new
