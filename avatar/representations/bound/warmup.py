"""Static warm-up of mesh-bound Gaussians (stage one of the paper; the GaussianAvatars baseline).

Loss: (1 - lambda) L1 + lambda D-SSIM + a L_s + b L_mu (visible Gaussians only), Adam
with the 3DGS exponential decay of the position learning rate, and binding-preserving
density control on a schedule given as fractions of the run. Checkpoints go to a
directory that survives a killed run; training resumes from the newest one.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from avatar.geometry.views import ViewSet
from avatar.losses import reconstruction_loss, reconstruction_terms
from avatar.posing import MeshSequence
from avatar.representations.bound.density import DensityConfig, DensityController
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.training.checkpoint import load_checkpoint, save_checkpoint
from avatar.training.frame_params import FrameParams
from avatar.training.loop import loop_state, loss_values, run_steps
from avatar.training.rendering import render_view
from avatar.training.schedule import exponential_lr, scaled_interval
from avatar.training.validation import ValidationConfig, Validator

CHECKPOINT = "warmup.pt"
UNKNOWN_PART_LABEL = 3  # keyed foreground whose part is unknown (see data_schemas.frames)


@dataclass(frozen=True)
class WarmupTrainConfig:
    """Warm-up hyperparameters (paper / GaussianAvatars values as defaults)."""

    steps: int
    lambda_dssim: float = 0.2  # lambda of (1 - lambda) L1 + lambda D-SSIM (paper)
    scale_weight: float = 1.0  # a, weight of L_s (paper)
    position_weight: float = 0.01  # b, weight of L_mu (paper)
    eps_s: float = 0.4  # L_s threshold on local scales, units of the triangle scale k (paper)
    eps_mu: float = 0.2  # L_mu threshold on local positions, units of k (paper)
    # Adam rate of the Gaussians' local positions (units of k) at the start (GaussianAvatars)
    lr_position_init: float = 5e-3
    lr_position_final: float = 5e-5  # and at the end: decayed exponentially over the steps (GaussianAvatars)
    lr_scale: float = 1.7e-2  # Adam rate of the log-scales (GaussianAvatars)
    lr_rotation: float = 1e-3  # of the quaternions (3DGS)
    lr_opacity: float = 5e-2  # of the opacity logits (3DGS)
    lr_color: float = 2.5e-3  # of the colours, degree-0 spherical harmonics (3DGS)
    densify_from: float = 0.02  # density control starts at this fraction of the steps (3DGS: 500 of 30k)
    densify_until: float = 0.5  # density control runs until this fraction of the steps (3DGS: 15k of 30k)
    densify_interval: float = 0.01  # fraction of the steps between densifications (3DGS: 100 of 30k)
    opacity_reset_interval: float = 0.1  # fraction of the steps between opacity resets (3DGS: 3k of 30k)
    # a Gaussian whose mean screen-space position gradient exceeds this is cloned or split (3DGS)
    grad_threshold: float = 2e-4
    max_gaussians: int = 1_000_000  # density control never grows the model beyond this
    checkpoint_every: int = 0  # steps; 0 = never
    log_every: int = 10  # steps between loss-curve points
    seed: int = 0
    # rasterizer: auto (gsplat on CUDA if installed; on CPU the compiled cpu backend if built, else torch), torch, cpu,
    # gsplat
    backend: str = "auto"

    def density(self) -> DensityConfig:
        s = self.steps
        return DensityConfig(
            densify_from=scaled_interval(self.densify_from, s),
            densify_until=scaled_interval(self.densify_until, s),
            densify_interval=scaled_interval(self.densify_interval, s),
            opacity_reset_interval=scaled_interval(self.opacity_reset_interval, s),
            grad_threshold=self.grad_threshold,
            max_gaussians=self.max_gaussians,
        )


#: the loss terms of the bound recipes' log rows (the keys of avatar.losses.reconstruction_terms)
LOSS_TERMS = ("l1", "dssim", "scale_reg", "position_reg")


@dataclass
class LogRow:
    step: int
    loss: float
    l1: float
    dssim: float
    scale_reg: float
    position_reg: float
    num_gaussians: int


Progress = Callable[[Iterable[int]], Iterator[int]]


def gaussian_param_groups(
    model: BoundGaussians, lr_position: float, lr_scale: float, lr_rotation: float, lr_opacity: float, lr_color: float
) -> list[dict]:
    """Adam parameter groups of the Gaussians, one per parameter, named after it."""
    return [
        {"params": [model.local_means], "lr": lr_position, "name": "local_means"},
        {"params": [model.log_scales], "lr": lr_scale, "name": "log_scales"},
        {"params": [model.quats], "lr": lr_rotation, "name": "quats"},
        {"params": [model.opacity_logits], "lr": lr_opacity, "name": "opacity_logits"},
        {"params": [model.sh_dc], "lr": lr_color, "name": "sh_dc"},
    ]


def _optimizer(model: BoundGaussians, cfg: WarmupTrainConfig) -> torch.optim.Adam:
    groups = gaussian_param_groups(
        model, cfg.lr_position_init, cfg.lr_scale, cfg.lr_rotation, cfg.lr_opacity, cfg.lr_color
    )
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


def render_frame(
    model: BoundGaussians,
    meshes: MeshSequence,
    views: ViewSet,
    frame: int,
    camera: int,
    backend: str = "auto",
    vertices: Tensor | None = None,
):  # the RenderOutput
    """Render the model on frame ``frame``'s meshes from view ``camera`` of ``views`` (``vertices`` (V, 3):
    that frame's posed vertices when they differ from ``meshes``', e.g. refined by :class:`FrameParams`)."""
    vertices = meshes.vertices[frame] if vertices is None else vertices
    means, scales, quats = model.world(vertices, meshes.faces)
    return render_view(means, quats, scales, model.opacities(), model.colors(), views, camera, backend), scales


@torch.no_grad()
def colors_from_views(means: Tensor, part_labels: Tensor, views: ViewSet, frame: int) -> Tensor:
    """Initial colours (N, 3): the mean pixel colour under each Gaussian's centre over the views of
    ``frame`` where the centre projects onto its own part (mask label ``part_labels`` (N,), or the
    unknown-part label 3); 0.5 grey where no view sees it. Short runs then start from the right
    colours instead of spending their steps on them."""
    n = means.shape[0]
    total, count = means.new_zeros(n, 3), means.new_zeros(n)
    size = views.size
    for c in range(views.num_cameras):
        cam = means @ views.world_to_cam[c, :3, :3].T + views.world_to_cam[c, :3, 3]
        z = cam[:, 2]
        uvw = cam @ views.K[c].T
        uv = torch.round(uvw[:, :2] / torch.where(z > 1e-6, z, torch.ones_like(z))[:, None]).long()
        inside = (z > 1e-6) & (uv >= 0).all(-1) & (uv < size).all(-1)
        u, v = uv[:, 0].clamp(0, size - 1), uv[:, 1].clamp(0, size - 1)
        label = views.labels[frame, c][v, u].long()
        ok = inside & ((label == part_labels) | (label == UNKNOWN_PART_LABEL))
        total[ok] += views.image(frame, c)[v[ok], u[ok]]
        count[ok] += 1
    return torch.where(count[:, None] > 0, total / count.clamp_min(1)[:, None], torch.full_like(total, 0.5))


def train_warmup(
    model: BoundGaussians,
    views: ViewSet,
    meshes: MeshSequence,
    cfg: WarmupTrainConfig,
    checkpoint_dir: Path | None = None,
    progress: Progress = iter,
    validator: Validator | None = None,
    params: FrameParams | None = None,
) -> list[LogRow]:
    """Optimise ``model`` in place for ``cfg.steps`` steps (fewer when ``validator`` stops it); returns the
    loss log. With ``params`` the meshes are posed from it and each step also refines the rendered frame's
    parameters (:mod:`avatar.training.frame_params`); the frames ``validator`` withholds are never refined.

    Samples one (frame, camera) pair per step uniformly over the frames ``validator`` leaves to training
    (default: no validation, every frame). With ``checkpoint_dir`` it resumes from ``warmup.pt`` there when
    present (the model is resized to match). The stop rule looks at the validations after density control.
    """
    gen = torch.Generator().manual_seed(cfg.seed)  # frames and cameras: drawn on the CPU on every device
    validator = validator if validator is not None else Validator(ValidationConfig(), views)
    optimizer = _optimizer(model, cfg)
    density = DensityController(cfg.density(), model.num_gaussians, device=model.local_means.device, seed=cfg.seed)
    extent = meshes.extent()
    log: list[LogRow] = []
    start = 0
    ckpt_path = checkpoint_dir / CHECKPOINT if checkpoint_dir is not None else None
    state = load_checkpoint(ckpt_path, _CHECKPOINT_KEYS, model.local_means.device) if ckpt_path is not None else None
    if state is not None:
        start, log = _restore(state, model, density, gen)
        optimizer = _optimizer(model, cfg)
        optimizer.load_state_dict(state["optimizer"])
        validator.load_state(state["validation"])
        if params is not None:
            params.load_state(state["params"])

    def posed(frame: int) -> Tensor | None:
        return params.vertices(frame) if params is not None else None

    def render(frame: int) -> Tensor:
        vertices = posed(frame)
        return torch.stack(
            [
                render_frame(model, meshes, views, frame, c, cfg.backend, vertices)[0].rgb
                for c in range(views.num_cameras)
            ]
        )

    def train_step(step: int) -> tuple[Tensor, dict[str, Tensor]]:
        frame = validator.sample_frame(gen)
        camera = int(torch.randint(views.num_cameras, (1,), generator=gen, device="cpu"))
        for group in optimizer.param_groups:
            if group["name"] == "local_means":
                group["lr"] = exponential_lr(step, cfg.lr_position_init, cfg.lr_position_final, cfg.steps)
        out, world_scales = render_frame(model, meshes, views, frame, camera, cfg.backend, posed(frame))
        visible = out.radii > 0
        gt, pred = views.target_and_render(out.rgb, frame, camera)
        terms = reconstruction_terms(
            pred, gt, torch.exp(model.log_scales), model.local_means, visible, cfg.eps_s, cfg.eps_mu
        )
        loss = reconstruction_loss(terms, cfg.lambda_dssim, cfg.scale_weight, cfg.position_weight)
        loss.backward()
        density.accumulate(out.grad2d_norm(), visible, views.size)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if params is not None:
            params.step(frame, validator.train_frames)
        density.step(step, model, optimizer, world_scales.detach(), extent)
        return loss, terms

    def log_row(step: int, outcome: tuple[Tensor, dict[str, Tensor]]) -> LogRow:
        loss, terms = outcome
        return LogRow(step, loss.item(), **loss_values(terms, LOSS_TERMS), num_gaussians=model.num_gaussians)

    def checkpoint(step: int) -> None:
        assert ckpt_path is not None
        _save_checkpoint(ckpt_path, step, model, optimizer, density, gen, log, validator, params)

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


_CHECKPOINT_KEYS = (
    "step",
    "model",
    "optimizer",
    "grad_sum",
    "count",
    "rng",
    "density_rng",
    "log",
    "validation",
    "params",
)


def _save_checkpoint(
    path: Path,
    step: int,
    model: BoundGaussians,
    optimizer: torch.optim.Optimizer,
    density: DensityController,
    gen: torch.Generator,
    log: list[LogRow],
    validator: Validator,
    params: FrameParams | None,
) -> None:
    """Everything needed to resume bit for bit (verified on load: :mod:`avatar.training.checkpoint`)."""
    save_checkpoint(
        path,
        {
            **loop_state(step, model, optimizer, gen, log, validator),
            "grad_sum": density.grad_sum,
            "count": density.count,
            "density_rng": density.generator.get_state(),
            "params": params.state() if params is not None else None,
        },
    )


def _restore(
    state: dict, model: BoundGaussians, density: DensityController, gen: torch.Generator
) -> tuple[int, list[LogRow]]:
    """Load a verified checkpoint into the model, density controller and sampler; (step, log so far)."""
    model.resize_like(state["model"])
    model.load_state_dict(state["model"])
    density.grad_sum, density.count = state["grad_sum"], state["count"]
    gen.set_state(state["rng"])
    density.generator.set_state(state["density_rng"])
    return int(state["step"]), [LogRow(**r) for r in state["log"]]
