"""Training of mesh-embedded Gaussians: the SplattingAvatar baseline (Shao et al., CVPR 2024).

The recipe of the public code (``initialneil/SplattingAvatar``):

- loss (``model/loss_base.py``, ``collect_loss``, weights from ``configs/splatting_avatar.yaml``):
  ``(1 - lambda_ssim) L1 + lambda_ssim (1 - SSIM) + lambda_rgb_mse MSE + lambda_perceptual LPIPS
  + lambda_scaling L_scale`` with ``lambda_ssim = 0.2``, ``lambda_rgb_mse = 10``,
  ``lambda_perceptual = 0.05`` (LPIPS-AlexNet: ``utils/loss_utils.py``, ``LPIPS.forward`` defaults to
  ``net_name='alex'``, inputs in [0, 1]) and ``L_scale`` = the mean of the largest world scale over the
  Gaussians whose largest scale exceeds ``thresh_scaling_max = 0.008`` and whose largest/smallest
  ratio exceeds ``thresh_scaling_ratio = 10`` (0 when there is none). ``lambda_scaling`` is 0 in the
  head config (``# 0.0 for head, 1.0 for instant avatar``) and 1.0 in ``configs/instant_avatar.yaml``
  (bodies); the default here is 1.0, since the capture holds an articulated hand (set
  ``scale_weight=0`` for the head recipe). The public code composites the target over a random
  background per step and masks LPIPS with the target's alpha; here targets come with the capture's
  fixed background and the losses see the whole crop, as the static baseline's;
- Adam (eps 1e-15) with learning rates ``_xyz`` (here barycentrics ``u, v`` and displacement ``d``):
  1.6e-4 decayed exponentially to 1.6e-6 over the run (``scheduler_args``; ``lr_delay_mult`` has no
  effect without delay steps), colour 2.5e-3, opacity 0.05, scaling 5e-3, rotation 1e-3;
- density control from step 100 every 100 until 15 000 of 30 000, opacity reset every 3 000,
  gradient threshold 2e-4, min opacity 0.005, ``percent_dense`` 0.01 (:mod:`avatar.representations.embedded.density`);
  here as fractions of the run. The scene extent is 2.0: ``train_splatting_avatar.py`` calls
  ``adaptive_density_control(render_pkg, iteration)``, whose ``cameras_extent`` defaults to 2.0 (the
  dataset's ``cameras_extent: 1.0`` is not passed on). ``optim.max_n_gauss`` is 150 000, but
  ``densify_and_prune`` reads ``model.max_n_gauss`` (commented out, so no cap); the cap here is
  150 000;
- triangle walk every ``triangle_walk_interval = 100`` steps (``update_trangle_walk``); here every
  Gaussian that left its triangle walks (:mod:`avatar.representations.embedded.walking`) and the Adam moments of the
  walked Gaussians' ``(u, v)`` are zeroed (the public code zeroes those of all Gaussians).

Structure as :mod:`avatar.representations.bound.warmup`: one random (frame, camera) per step, verified checkpoints
that resume bit for bit, a :class:`LogRow` list. Calling :func:`train_splatting` again on a trained
model with ``densify_until = 0`` continues without density control (walking goes on).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import torch
from torch import Tensor

from avatar.geometry.views import ViewSet
from avatar.metrics import LPIPS, dssim_loss
from avatar.metrics.lpips_weights import Net
from avatar.posing import MeshSequence
from avatar.render.gaussians import RenderOutput
from avatar.representations.embedded.density import EmbeddedDensityConfig, EmbeddedDensityController
from avatar.representations.embedded.embedding import EmbeddedGaussians
from avatar.training.checkpoint import load_checkpoint, save_checkpoint
from avatar.training.loop import loop_state, loss_values, run_steps
from avatar.training.rendering import render_view
from avatar.training.schedule import exponential_lr, scaled_interval
from avatar.training.validation import ValidationConfig, Validator

CHECKPOINT = "splatting.pt"
_POSITION_GROUPS = ("barycentric", "displacement")


@dataclass(frozen=True)
class SplattingConfig:
    """SplattingAvatar hyperparameters (public-code values as defaults; schedule points as fractions
    of ``steps`` except ``walk_every``, in steps)."""

    steps: int
    lambda_dssim: float = 0.2  # D-SSIM weight (lambda_ssim)
    lambda_mse: float = 10.0  # MSE weight (configs/splatting_avatar.yaml: lambda_rgb_mse)
    lambda_lpips: float = 0.05  # LPIPS weight (lambda_perceptual)
    lpips_net: str = "alex"  # the LPIPS network (alex, the public code's)
    scale_weight: float = 1.0  # L_scale weight (lambda_scaling: 0 for heads, 1 for bodies; the hand is articulated)
    scale_threshold: float = 0.008  # L_scale penalises scales above this, metres (scaling_threshold)
    scale_ratio_threshold: float = 10.0  # and largest / smallest scale ratios above this
    # Adam rate of u, v (barycentric units) and d (metres) at the start (position_lr_init)
    lr_position_init: float = 1.6e-4
    lr_position_final: float = 1.6e-6  # and at the end: decayed exponentially over the steps (position_lr_final)
    lr_scale: float = 5e-3  # Adam rate of the log-scales (scaling_lr)
    lr_rotation: float = 1e-3  # of the quaternions (rotation_lr)
    lr_opacity: float = 5e-2  # of the opacity logits (opacity_lr)
    lr_color: float = 2.5e-3  # of the colours (feature_lr)
    densify_from: float = 100 / 30_000  # density control from this fraction of the steps (public: 100 of 30k)
    densify_until: float = 0.5  # 0 disables density control (and the opacity resets)
    densify_interval: float = 100 / 30_000  # fraction of the steps between densifications (public: 100 of 30k)
    opacity_reset_interval: float = 0.1
    # screen-space gradient above which a Gaussian is cloned or split (densify_grad_threshold)
    grad_threshold: float = 2e-4
    scene_extent: float = 2.0  # the public code's cameras_extent as used, metres; 0: the meshes' bounding radius
    max_gaussians: int = 150_000
    walk_every: int = 100  # steps between triangle walks (triangle_walk_interval)
    max_hops: int = 64  # most triangles one walk may cross
    backend: str = "auto"
    seed: int = 0
    log_every: int = 10
    checkpoint_every: int = 0  # steps; 0 = never

    def density(self) -> EmbeddedDensityConfig:
        """The density schedule in steps (``densify_until = 0`` when disabled)."""

        def at(fraction: float) -> int:
            return scaled_interval(fraction, self.steps)

        until = scaled_interval(self.densify_until, self.steps, minimum=0) if self.densify_until > 0 else 0
        return EmbeddedDensityConfig(
            at(self.densify_from),
            until,
            at(self.densify_interval),
            at(self.opacity_reset_interval),
            grad_threshold=self.grad_threshold,
            max_gaussians=self.max_gaussians,
        )


@dataclass
class LogRow:
    """One row of the loss curve; ``walked`` sums the Gaussians that changed triangle over the walks
    (and density steps) since the previous row."""

    step: int
    loss: float
    l1: float
    dssim: float
    mse: float
    lpips: float
    scale_reg: float
    num_gaussians: int
    walked: int


Progress = Callable[[Iterable[int]], Iterator[int]]


def render_splatting(
    model: EmbeddedGaussians, meshes: MeshSequence, views: ViewSet, frame: int, camera: int, backend: str = "auto"
) -> tuple[RenderOutput, Tensor]:
    """Render ``model`` on frame ``frame``'s meshes from camera ``camera``; also the world scales (N, 3)."""
    means, scales, quats = model.world(meshes.vertices[frame], meshes.faces)
    return render_view(means, quats, scales, model.opacities(), model.colors(), views, camera, backend), scales


def scale_penalty(world_scales: Tensor, max_threshold: float, ratio_threshold: float) -> Tensor:
    """SplattingAvatar's ``L_scale``: mean largest scale of the needle-like Gaussians (largest scale above
    ``max_threshold`` and largest/smallest above ``ratio_threshold``) among (N, 3) world scales; 0 if none."""
    largest = world_scales.amax(-1)
    ratio = largest / world_scales.amin(-1).clamp_min(1e-30)
    needles = (largest > max_threshold) & (ratio > ratio_threshold)
    return largest[needles].mean() if bool(needles.any()) else world_scales.sum() * 0.0


def splatting_terms(
    pred: Tensor, gt: Tensor, world_scales: Tensor, cfg: SplattingConfig, lpips: LPIPS | None
) -> dict[str, Tensor]:
    """``l1``, ``dssim``, ``mse``, ``lpips`` (0 without a module) of a render ``pred`` against ``gt`` (S, S, 3)
    in [0, 1], and ``scale_reg`` of the (N, 3) world scales."""
    pred_chw, gt_chw = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    perceptual = lpips(pred_chw.float(), gt_chw.float(), unit_range=True)[0] if lpips is not None else pred.sum() * 0.0
    return {
        "l1": (pred - gt).abs().mean(),
        "dssim": dssim_loss(pred_chw, gt_chw),
        "mse": (pred - gt).square().mean(),
        "lpips": perceptual,
        "scale_reg": scale_penalty(world_scales, cfg.scale_threshold, cfg.scale_ratio_threshold),
    }


def splatting_loss(terms: dict[str, Tensor], cfg: SplattingConfig) -> Tensor:
    """The weighted sum of :func:`splatting_terms` (module docstring)."""
    return (
        (1 - cfg.lambda_dssim) * terms["l1"]
        + cfg.lambda_dssim * terms["dssim"]
        + cfg.lambda_mse * terms["mse"]
        + cfg.lambda_lpips * terms["lpips"]
        + cfg.scale_weight * terms["scale_reg"]
    )


def splatting_param_groups(model: EmbeddedGaussians, cfg: SplattingConfig) -> list[dict]:
    """Adam groups, one per parameter and named after it."""
    rates = {
        "barycentric": cfg.lr_position_init,
        "displacement": cfg.lr_position_init,
        "log_scales": cfg.lr_scale,
        "quats": cfg.lr_rotation,
        "opacity_logits": cfg.lr_opacity,
        "sh_dc": cfg.lr_color,
    }
    return [{"params": [getattr(model, name)], "lr": lr, "name": name} for name, lr in rates.items()]


def _optimizer(model: EmbeddedGaussians, cfg: SplattingConfig) -> torch.optim.Adam:
    return torch.optim.Adam(splatting_param_groups(model, cfg), lr=0.0, eps=1e-15)


def _set_position_lr(optimizer: torch.optim.Optimizer, step: int, cfg: SplattingConfig) -> None:
    lr = exponential_lr(step, cfg.lr_position_init, cfg.lr_position_final, cfg.steps)
    for group in optimizer.param_groups:
        if group["name"] in _POSITION_GROUPS:
            group["lr"] = lr


def _walk(model: EmbeddedGaussians, optimizer: torch.optim.Optimizer, max_hops: int) -> int:
    """Walk the Gaussians that left their triangles; zero the ``(u, v)`` Adam moments of those that
    changed triangle (they were expressed in the old triangle). Returns how many changed."""
    changed = model.walk(max_hops)
    state = optimizer.state.get(model.barycentric)
    if state and bool(changed.any()):
        for key in ("exp_avg", "exp_avg_sq"):
            state[key][changed] = 0.0
    return int(changed.sum())


def train_splatting(
    model: EmbeddedGaussians,
    views: ViewSet,
    meshes: MeshSequence,
    cfg: SplattingConfig,
    checkpoint_dir: Path | None = None,
    progress: Progress = iter,
    validator: Validator | None = None,
) -> list[LogRow]:
    """Optimise ``model`` in place for ``cfg.steps`` steps (fewer when ``validator`` stops it, which looks at
    the validations after density control); returns the loss log.

    Draws frames from those ``validator`` leaves to training (default: no validation, every frame). With
    ``checkpoint_dir`` it resumes from ``splatting.pt`` there when present (the model is resized to match)
    and writes one every ``cfg.checkpoint_every`` steps.
    """
    device = model.barycentric.device
    gen = torch.Generator().manual_seed(cfg.seed)
    validator = validator if validator is not None else Validator(ValidationConfig(), views)
    density = EmbeddedDensityController(cfg.density(), model.num_gaussians, seed=cfg.seed, device=device)
    # cast: the config field is a plain str (the config schemas take no Literal); LPIPS checks the name
    lpips = LPIPS(cast(Net, cfg.lpips_net)).to(device) if cfg.lambda_lpips > 0 else None
    extent = cfg.scene_extent if cfg.scene_extent > 0 else meshes.extent()
    optimizer = _optimizer(model, cfg)
    log: list[LogRow] = []
    start, walked = 0, 0
    ckpt_path = checkpoint_dir / CHECKPOINT if checkpoint_dir is not None else None
    state = load_checkpoint(ckpt_path, _CHECKPOINT_KEYS, device) if ckpt_path is not None else None
    if state is not None:
        model.resize_like(state["model"])
        model.load_state_dict(state["model"])
        optimizer = _optimizer(model, cfg)
        optimizer.load_state_dict(state["optimizer"])
        density.load_state(state["density"])
        gen.set_state(state["rng"])
        start, walked, log = int(state["step"]), int(state["walked"]), [LogRow(**r) for r in state["log"]]
        validator.load_state(state["validation"])

    def render(frame: int) -> Tensor:
        return torch.stack(
            [render_splatting(model, meshes, views, frame, c, cfg.backend)[0].rgb for c in range(views.num_cameras)]
        )

    def train_step(step: int) -> tuple[Tensor, dict[str, Tensor]]:
        nonlocal walked
        frame = validator.sample_frame(gen)
        camera = int(torch.randint(views.num_cameras, (1,), generator=gen, device="cpu"))
        _set_position_lr(optimizer, step, cfg)
        out, world_scales = render_splatting(model, meshes, views, frame, camera, cfg.backend)
        gt, pred = views.target_and_render(out.rgb, frame, camera)
        terms = splatting_terms(pred, gt, world_scales, cfg, lpips)
        loss = splatting_loss(terms, cfg)
        loss.backward()
        density.accumulate(step, out.grad2d_norm(), out.radii, views.size)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        walked += density.step(step, model, optimizer, extent)["walked"]
        if cfg.walk_every > 0 and step % cfg.walk_every == 0:
            walked += _walk(model, optimizer, cfg.max_hops)
        return loss, terms

    def log_row(step: int, outcome: tuple[Tensor, dict[str, Tensor]]) -> LogRow:
        nonlocal walked
        loss, terms = outcome
        row = LogRow(
            step,
            loss.item(),
            **loss_values(terms, ("l1", "dssim", "mse", "lpips", "scale_reg")),
            num_gaussians=model.num_gaussians,
            walked=walked,
        )
        walked = 0
        return row

    def checkpoint(step: int) -> None:
        assert ckpt_path is not None
        save_checkpoint(
            ckpt_path,
            {
                **loop_state(step, model, optimizer, gen, log, validator),
                "density": density.state(),
                "walked": walked,
            },
        )

    run_steps(
        progress(validator.begin(start, cfg.steps, density.cfg.densify_until, render)),
        train_step,
        validator,
        render,
        log,
        log_row,
        cfg.log_every,
        checkpoint if ckpt_path is not None else None,
        cfg.checkpoint_every,
        loss_of=lambda outcome: outcome[0],
        checkpoint_file=ckpt_path,
    )
    return log


_CHECKPOINT_KEYS = ("step", "model", "optimizer", "density", "rng", "walked", "log", "validation")
