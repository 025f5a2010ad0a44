"""Adaptive density control (3DGS clone / split / prune / opacity reset) that keeps the mesh binding.

- clone: a Gaussian with a large view-space positional gradient and a small
  world scale is duplicated in place (same parent triangle);
- split: such a Gaussian with a large scale is replaced by two children drawn
  from it, scales divided by 1.6, both bound to the parent's triangle;
- prune: Gaussians with opacity below ``min_opacity`` (or non-finite
  parameters) are removed, except that every triangle keeps at least its most
  opaque Gaussian (GaussianAvatars), so no triangle is ever left empty (a kept
  Gaussian with non-finite parameters restarts as a faint one at the centre);
- opacity reset: opacities are clamped to ``reset_opacity``.

Adam moments follow every change: copied for clones and children, dropped for
removed Gaussians, zeroed for the reset opacities.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from avatar.representations.bound.gaussians import PARAM_NAMES, BoundGaussians, inverse_sigmoid


@dataclass(frozen=True)
class DensityConfig:
    """Schedule and thresholds (iterations are optimizer steps)."""

    densify_from: int
    densify_until: int
    densify_interval: int
    opacity_reset_interval: int
    grad_threshold: float = 2e-4  # 3DGS threshold on the NDC-space positional gradient
    percent_dense: float = 0.01  # clone below, split above this fraction of the scene extent
    min_opacity: float = 0.005
    reset_opacity: float = 0.01
    max_gaussians: int = 1_000_000


class DensityController:
    """Accumulates view-space gradients between densification steps and applies them."""

    def __init__(
        self, cfg: DensityConfig, num_gaussians: int, device: torch.device | None = None, seed: int = 0
    ) -> None:
        self.cfg = cfg
        self.grad_sum = torch.zeros(num_gaussians, device=device)
        self.count = torch.zeros(num_gaussians, device=device)
        # Split children are drawn from this generator, so a resumed run repeats them exactly.
        self.generator = torch.Generator(device=device or "cpu").manual_seed(seed)

    def accumulate(self, grad2d_px: Tensor, visible: Tensor, image_size: int) -> None:
        """Add one view's (N,) pixel-space positional gradient norms for the (N,) visible Gaussians.

        Pixel gradients are converted to the NDC convention of 3DGS (multiplied by size / 2) so
        that the reference threshold 2e-4 applies at any resolution.
        """
        ndc = grad2d_px.detach() * (image_size / 2)
        self.grad_sum += torch.where(visible, ndc, torch.zeros_like(ndc))
        self.count += visible.float()

    def step(
        self,
        iteration: int,
        model: BoundGaussians,
        optimizer: torch.optim.Optimizer,
        world_scales: Tensor,
        extent: float,
    ) -> dict[str, int]:
        """Apply the schedule after optimizer step ``iteration`` (1-based). Returns counts of what changed."""
        c = self.cfg
        done = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        in_window = c.densify_from <= iteration <= c.densify_until
        if in_window and iteration % c.densify_interval == 0:
            done.update(self._densify_and_prune(model, optimizer, world_scales.detach(), extent))
        if in_window and iteration % c.opacity_reset_interval == 0:
            reset_opacity(model, optimizer, c.reset_opacity)
            done["reset"] = model.num_gaussians
        return done

    def _densify_and_prune(
        self, model: BoundGaussians, optimizer: torch.optim.Optimizer, world_scales: Tensor, extent: float
    ) -> dict[str, int]:
        c = self.cfg
        grads = self.grad_sum / self.count.clamp_min(1)
        room = max(c.max_gaussians - model.num_gaussians, 0)
        hot = grads >= c.grad_threshold
        big = world_scales.max(dim=-1).values > c.percent_dense * extent
        clone_idx = torch.nonzero(hot & ~big).flatten()[:room]
        split_idx = torch.nonzero(hot & big).flatten()[: max(room - len(clone_idx), 0)]
        n = model.num_gaussians
        children = _split_children(model, split_idx, self.generator)
        _append(model, optimizer, clone_idx, {})
        _append(model, optimizer, split_idx.repeat(2), children)
        # Parents of split Gaussians go away together with the transparent ones.
        remove = torch.zeros(model.num_gaussians, dtype=torch.bool, device=model.binding.device)
        remove[split_idx] = True
        remove |= prunable(model, c.min_opacity)
        remove &= ~last_of_triangle(model, remove)
        _keep(model, optimizer, ~remove)
        _reinitialise_broken(model)
        self.grad_sum = torch.zeros(model.num_gaussians, device=self.grad_sum.device)
        self.count = torch.zeros(model.num_gaussians, device=self.count.device)
        grown = len(clone_idx) + 2 * len(split_idx)
        return {
            "cloned": len(clone_idx),
            "split": len(split_idx),
            "pruned": int(remove.sum()) - len(split_idx),
            "total_before": n,
            "total_after": n + grown - int(remove.sum()),
        }


def prunable(model: BoundGaussians, min_opacity: float) -> Tensor:
    """(N,) bool: too transparent, or any parameter non-finite."""
    bad = torch.zeros(model.num_gaussians, dtype=torch.bool, device=model.binding.device)
    for name in PARAM_NAMES:
        p = getattr(model, name).detach()
        bad |= ~torch.isfinite(p.reshape(model.num_gaussians, -1)).all(-1)
    return bad | (model.opacities().detach() < min_opacity)


def last_of_triangle(model: BoundGaussians, remove: Tensor) -> Tensor:
    """(N,) bool marking, for each triangle whose Gaussians would all be removed, its most opaque one."""
    num_tri = int(model.binding.max()) + 1 if model.num_gaussians else 0
    survivors = torch.zeros(num_tri, dtype=torch.long, device=remove.device).index_add_(
        0, model.binding, (~remove).long()
    )
    orphaned = survivors[model.binding] == 0
    score = torch.nan_to_num(model.opacity_logits.detach(), nan=-1e30)
    score = torch.where(orphaned, score, torch.full_like(score, -float("inf")))
    best = torch.full((num_tri,), -float("inf"), dtype=score.dtype, device=score.device)
    best = best.scatter_reduce(0, model.binding, score, reduce="amax")
    keep = orphaned & (score == best[model.binding])
    # Ties: keep only the first Gaussian per triangle.
    first = torch.zeros(model.num_gaussians, dtype=torch.bool, device=remove.device)
    idx = torch.nonzero(keep).flatten()
    if len(idx):
        tri = model.binding[idx]
        _, order = torch.sort(tri, stable=True)
        tri_sorted = tri[order]
        is_first = torch.ones_like(tri_sorted, dtype=torch.bool)
        is_first[1:] = tri_sorted[1:] != tri_sorted[:-1]
        first[idx[order[is_first]]] = True
    return first


def _split_children(model: BoundGaussians, idx: Tensor, generator: torch.Generator) -> dict[str, Tensor]:
    """Parameters of two children per split Gaussian (2 * len(idx) rows, in ``idx.repeat(2)`` order)."""
    idx2 = idx.repeat(2)
    scales = torch.exp(model.log_scales.detach()[idx2])
    q = model.quats.detach()[idx2]
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    noise = torch.randn(scales.shape, generator=generator, dtype=scales.dtype, device=scales.device)
    offsets = _rotate(q, noise * scales)
    return {
        "local_means": model.local_means.detach()[idx2] + offsets,
        "log_scales": torch.log(scales / 1.6),
    }


def _rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors v (M, 3) by unit quaternions q (M, 4) (w, x, y, z)."""
    w, xyz = q[:, :1], q[:, 1:]
    t = 2 * torch.linalg.cross(xyz, v)
    return v + w * t + torch.linalg.cross(xyz, t)


def _replace(
    model: BoundGaussians,
    optimizer: torch.optim.Optimizer,
    name: str,
    value: Tensor,
    edit_state: Callable[[Tensor], Tensor],
) -> None:
    """Swap parameter ``name`` for ``value``, carrying its Adam moments through ``edit_state``."""
    old = getattr(model, name)
    new = nn.Parameter(value.contiguous())
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state:
                    optimizer.state[new] = {
                        k: (edit_state(v) if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in state.items()
                    }
    setattr(model, name, new)


def _append(model: BoundGaussians, optimizer: torch.optim.Optimizer, src: Tensor, overrides: dict[str, Tensor]) -> None:
    """Append copies of Gaussians ``src`` (M,), with some parameters overridden; new moments are zero."""
    if len(src) == 0:
        return
    m = len(src)
    for name in PARAM_NAMES:
        p = getattr(model, name).detach()
        extra = overrides.get(name, p[src])
        _replace(
            model,
            optimizer,
            name,
            torch.cat([p, extra]),
            lambda s: torch.cat([s, torch.zeros((m, *s.shape[1:]), dtype=s.dtype, device=s.device)]),
        )
    model.binding = torch.cat([model.binding, model.binding[src]])
    model.part = torch.cat([model.part, model.part[src]])


def _keep(model: BoundGaussians, optimizer: torch.optim.Optimizer, mask: Tensor) -> None:
    """Keep only the Gaussians where ``mask`` (N,) is true."""
    for name in PARAM_NAMES:
        _replace(model, optimizer, name, getattr(model, name).detach()[mask], lambda s: s[mask])
    model.binding = model.binding[mask]
    model.part = model.part[mask]


@torch.no_grad()
def _reinitialise_broken(model: BoundGaussians) -> None:
    """Gaussians kept only so their triangle is not empty, whose parameters are non-finite, restart
    as a small faint Gaussian at the triangle centre."""
    broken = torch.zeros(model.num_gaussians, dtype=torch.bool, device=model.binding.device)
    for name in PARAM_NAMES:
        broken |= ~torch.isfinite(getattr(model, name).reshape(model.num_gaussians, -1)).all(-1)
    if not broken.any():
        return
    model.local_means[broken] = 0.0
    model.log_scales[broken] = -1.0
    model.quats[broken] = model.quats.new_tensor([1.0, 0.0, 0.0, 0.0])
    model.opacity_logits[broken] = inverse_sigmoid(model.opacity_logits.new_tensor(0.05))
    model.sh_dc[broken] = 0.0


def reset_opacity(model: BoundGaussians, optimizer: torch.optim.Optimizer, ceiling: float) -> None:
    """Clamp every opacity to at most ``ceiling`` and zero its Adam moments."""
    logits = model.opacity_logits.detach()
    capped = torch.minimum(logits, inverse_sigmoid(torch.tensor(ceiling, dtype=logits.dtype, device=logits.device)))
    _replace(model, optimizer, "opacity_logits", capped, torch.zeros_like)
