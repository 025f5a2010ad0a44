"""Stage two of the paper: train H, I, PointNet++, the point features and the Gaussians together.

Loss (paper, Eq. 13): ``(1 - lambda) L1 + lambda D-SSIM + a L_s + b L_mu + c L_patch`` with L_s and L_mu on
the visible Gaussians' local scales and positions *including their deltas*, and L_patch the LPIPS-VGG
distance on the hand's box and on the overlap of the hand and face boxes (from the part masks). Adam:
MLPs (and PointNet++) at 1e-3 and point features at 2.5e-3, both with the 3DGS exponential decay; the
Gaussians continue at the learning rates the warm-up ended with. Frames with contact are drawn first with
probability ``contact_fraction`` (the paper oversamples them; how much it does not say), lowered where a contact frame
would be drawn more than ``max_contact_emphasis`` times as often as a frame without contact
(:func:`contact_draw_probability`).
Checkpoints resume bit for bit, like the warm-up's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from avatar.dynamic.conditioning import Conditioning, SequenceConditioning
from avatar.geometry.views import FACE_LABEL, HAND_LABEL, ViewSet
from avatar.losses import patch_perceptual_loss, reconstruction_loss, reconstruction_terms
from avatar.metrics.lpips import LPIPS
from avatar.posing import MeshSequence
from avatar.preprocess.crops import label_box, overlap_box
from avatar.representations.bound.dynamic_model import DynamicAvatar, DynamicFrame
from avatar.representations.bound.warmup import LOSS_TERMS, gaussian_param_groups
from avatar.training.checkpoint import load_checkpoint, save_checkpoint
from avatar.training.frame_params import FrameParams
from avatar.training.loop import loop_state, loss_values, run_steps
from avatar.training.rendering import rasterize
from avatar.training.schedule import exponential_lr
from avatar.training.selection import BestStep, Selection, SelectionConfig, select
from avatar.training.validation import ValidationConfig, Validator, draw_frame

CHECKPOINT = "dynamic.pt"


@dataclass(frozen=True)
class DynamicTrainConfig:
    """Stage-two hyperparameters (paper values as defaults)."""

    steps: int
    lambda_dssim: float = 0.2  # lambda (paper)
    scale_weight: float = 1.0  # a, L_s (paper)
    position_weight: float = 0.01  # b, L_mu (paper)
    # c, L_patch: LPIPS-VGG on the hand box and the hand-face overlap (paper; 0: "w/o L_patch")
    patch_weight: float = 0.1
    eps_s: float = 0.4  # (paper)
    eps_mu: float = 0.2  # (paper)
    lr_mlp: float = 1e-3  # MLPs and PointNet++ (paper)
    lr_point_features: float = 2.5e-3  # P_i (paper)
    lr_decay: float = 0.1  # final / initial learning rate of the MLPs and P_i (3DGS-style exponential decay)
    lr_position: float = 5e-5  # Adam rate of the Gaussians' local positions, constant: where the warm-up's decay ended
    lr_scale: float = 1.7e-2  # of their log-scales, as in the warm-up
    lr_rotation: float = 1e-3  # of their quaternions, as in the warm-up
    lr_opacity: float = 5e-2  # of their opacity logits, as in the warm-up
    lr_color: float = 2.5e-3  # of their colours, as in the warm-up
    # probability of drawing a contact frame first, else any frame (the paper oversamples contact frames; 0: frames
    # uniformly)
    contact_fraction: float = 0.5
    # lowers contact_fraction so that a contact frame is drawn at most this many times as often as a frame without
    # contact (with few contact frames the Gaussians fit their tracking error; docs/explanation/dynamic-model.md)
    max_contact_emphasis: float = 3.0
    patch_min_size: int = 32  # L_patch boxes grow to at least this many pixels a side
    checkpoint_every: int = 0
    log_every: int = 10  # steps between loss-curve points
    seed: int = 0
    backend: str = "auto"  # rasterizer, as stage.warmup.backend
    selection: SelectionConfig = SelectionConfig()  # keep the best validation step and the modules it needs

    def problems(self) -> list[str]:
        """Range problems of the settings that have a range beyond non-negative, one line each, keyed by field."""
        problems = []
        if not 0.0 <= self.contact_fraction <= 1.0:  # also refuses NaN
            problems.append(
                f"contact_fraction={self.contact_fraction:g}: must lie in [0, 1] (the share of steps on contact frames)"
            )
        if not 1.0 <= self.max_contact_emphasis < math.inf:  # also refuses NaN
            problems.append(
                f"max_contact_emphasis={self.max_contact_emphasis:g}: must be >= 1 and finite (how many times as often "
                "as a frame without contact a contact frame may be drawn; 1 draws uniformly)"
            )
        return problems + [f"selection.{problem}" for problem in self.selection.problems()]


@dataclass
class DynamicLogRow:
    step: int
    loss: float
    l1: float
    dssim: float
    scale_reg: float
    position_reg: float
    patch: float
    interaction_evaluations: int


@dataclass
class DynamicTrainResult:
    """The loss log and the cost counters of a run (``seconds``: forward time per component, summed), what
    the selection kept (None when ``cfg.selection`` is off) and the contact-frame draw probability used."""

    log: list[DynamicLogRow]
    interaction_evaluations: int
    interaction_steps: int
    seconds: dict[str, float]
    selection: Selection | None = None
    contact_probability: float = 0.0


Progress = Callable[[Iterable[int]], Iterator[int]]
_MLP_GROUPS = ("hand_geo", "hand_app", "interaction", "pointnet")


def _optimizer(model: DynamicAvatar, cfg: DynamicTrainConfig) -> torch.optim.Adam:
    groups = gaussian_param_groups(
        model.gaussians, cfg.lr_position, cfg.lr_scale, cfg.lr_rotation, cfg.lr_opacity, cfg.lr_color
    )
    groups.append({"params": [model.point_features], "lr": cfg.lr_point_features, "name": "point_features"})
    for name in _MLP_GROUPS:
        module = getattr(model, name)
        if module is not None:
            groups.append({"params": list(module.parameters()), "lr": cfg.lr_mlp, "name": name})
    # fused: one pass per tensor instead of a dozen operations on each of the ~300 (draft: 7 ms a step instead of
    # 20 for the loop, 15 for foreach; the same update to rounding, about 1e-8)
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


def _set_learning_rates(optimizer: torch.optim.Optimizer, cfg: DynamicTrainConfig, step: int) -> None:
    for group in optimizer.param_groups:
        if group["name"] in _MLP_GROUPS:
            group["lr"] = exponential_lr(step, cfg.lr_mlp, cfg.lr_mlp * cfg.lr_decay, cfg.steps)
        elif group["name"] == "point_features":
            group["lr"] = exponential_lr(step, cfg.lr_point_features, cfg.lr_point_features * cfg.lr_decay, cfg.steps)


def render_dynamic(
    model: DynamicAvatar,
    cond: SequenceConditioning,
    meshes: MeshSequence,
    views: ViewSet,
    frame: int,
    camera: int,
    backend: str = "auto",
) -> tuple[object, DynamicFrame]:
    """(RenderOutput, DynamicFrame) of ``frame`` from view ``camera``, as evaluated (the most probable
    PointNet++ sample)."""
    g = model(cond.frame(frame), meshes.vertices[frame])
    return rasterize(g, views, camera, backend), g


def patch_boxes(labels: np.ndarray) -> list[np.ndarray]:
    """The boxes L_patch looks at in a crop's part labels (S, S): the hand's, and the overlap of the hand's
    and the face's (each only where present)."""
    hand, face = label_box(labels, HAND_LABEL), label_box(labels, FACE_LABEL)
    return [b for b in (hand, overlap_box(hand, face)) if b is not None]


def contact_draw_probability(
    frames: np.ndarray, contact: np.ndarray, contact_fraction: float, max_emphasis: float
) -> float:
    """The probability with which :func:`sample_frame` draws from the contact frames first: ``contact_fraction``,
    lowered so that no contact frame is drawn more than ``max_emphasis`` times as often as a frame without contact.

    With ``k`` contact frames among the ``K`` training frames ``frames`` (``contact``: (T,) bool over the sequence)
    and probability ``p``, a contact frame gets ``p / k + (1 - p) / K`` of the steps and any other frame
    ``(1 - p) / K``, so a contact frame is drawn ``e(p) = 1 + p K / ((1 - p) k)`` times as often. The paper
    oversamples contact frames because they are rare in a video, to give them enough steps; a contact frame is still
    one frame of the video. Uncapped, the emphasis grows with ``K / k`` (one contact frame of six took 58 % of the
    steps, ``e`` = 7), and with fitted tracking the Gaussians then fit those frames' tracking error instead of the
    person. The cap ``e(p) <= R`` gives ``p <= (R - 1) k / (K + (R - 1) k)``, whatever the capture's size; ``R`` = 3
    is the emphasis ``p`` = 0.5 gives when half the frames touch (``e`` = 1 + K / k = 3), the project's captures.
    """
    k, total = int(contact[frames].sum()), len(frames)
    if k == 0 or k == total:  # nothing to oversample: every draw is uniform over the frames either way
        return contact_fraction
    capped = (max_emphasis - 1.0) * k / (total + (max_emphasis - 1.0) * k)
    return min(contact_fraction, capped)


def sample_frame(gen: torch.Generator, frames: np.ndarray, contact: np.ndarray, contact_fraction: float) -> int:
    """One of the training frames ``frames`` (K,): with probability ``contact_fraction`` one of those with
    contact (``contact``: (T,) bool over the whole sequence), if any, else any of them."""
    contact_ids = frames[contact[frames]]
    draw = float(torch.rand((), generator=gen, device="cpu"))
    if contact_ids.size and draw < contact_fraction:
        return draw_frame(gen, contact_ids)
    return draw_frame(gen, frames)


def train_dynamic(
    model: DynamicAvatar,
    views: ViewSet,
    meshes: MeshSequence,
    cond: SequenceConditioning,
    contact: np.ndarray,
    cfg: DynamicTrainConfig,
    checkpoint_dir: Path | None = None,
    progress: Progress = iter,
    lpips: LPIPS | None = None,
    validator: Validator | None = None,
    params: FrameParams | None = None,
) -> DynamicTrainResult:
    """Optimise ``model`` in place for ``cfg.steps`` steps (fewer when ``validator`` stops it) on the frames of
    ``views``/``meshes``/``cond`` that ``validator`` leaves to training (default: no validation, every frame).

    Args:
        contact: (T,) bool, frames with hand-face contact (oversampled).
        checkpoint_dir: resume from ``dynamic.pt`` there when present; save every ``cfg.checkpoint_every``.
        lpips: the L_patch network (default LPIPS-VGG with the offline weights).
        validator: validates the model as evaluated (:func:`render_dynamic`) on its withheld frames; with
            ``cfg.selection.enabled`` the model left in ``model`` is the one the selection kept
            (:mod:`avatar.training.selection`), which needs validation.
        params: pose the meshes and the conditioning from it and refine the rendered frame's parameters each
            step (:mod:`avatar.training.frame_params`); with the selection, the parameters of the kept step
            are kept with it.
    """
    gen = torch.Generator().manual_seed(cfg.seed)  # frames, cameras and PointNet++'s sample: drawn on the CPU
    validator = validator if validator is not None else Validator(ValidationConfig(), views)
    if cfg.selection.enabled and not validator.cfg.enabled:
        raise ValueError(
            "stage two selects what it keeps on validation frames: set stage.dynamic.validation.every "
            "> 0, or stage.dynamic.select.enabled=false"
        )
    best = BestStep() if cfg.selection.enabled else None
    device = model.mu_cano.device  # the run's: the model, the crops, the meshes and the conditioning are there
    if lpips is None and cfg.patch_weight > 0:  # the VGG layers cost time to build: only where L_patch counts
        lpips = LPIPS("vgg")
    if lpips is not None:
        lpips.to(device)
    labels = views.labels.cpu()  # the part masks the patch boxes are cut from, read on the host every step
    optimizer = _optimizer(model, cfg)
    result = DynamicTrainResult([], 0, 0, {"model": 0.0, "render": 0.0, "loss": 0.0, "backward": 0.0})
    start = 0
    ckpt_path = checkpoint_dir / CHECKPOINT if checkpoint_dir is not None else None
    state = load_checkpoint(ckpt_path, _CHECKPOINT_KEYS, device) if ckpt_path is not None else None
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        gen.set_state(state["rng"])
        start = int(state["step"])
        result.log = [DynamicLogRow(**r) for r in state["log"]]
        result.interaction_evaluations, result.interaction_steps = state["interaction"]
        validator.load_state(state["validation"])
        if best is not None and state["best"] is not None:
            best.load_state(state["best"])
        if params is not None:
            params.load_state(state["params"])

    def inputs(frame: int) -> tuple[Conditioning, Tensor]:  # the frame's conditioning and posed vertices
        if params is None:
            return cond.frame(frame), meshes.vertices[frame]
        return params.conditioning(frame), params.vertices(frame)

    def render(frame: int) -> Tensor:  # as evaluated: the most probable PointNet++ sample, posed once
        g = model(*inputs(frame))
        return torch.stack([rasterize(g, views, c, cfg.backend).rgb for c in range(views.num_cameras)])

    def offer_validation() -> None:  # a new validation point is a candidate of the selection
        if best is not None and validator.curve and validator.curve[-1].step > best.offered:
            best.offer(validator.curve[-1].step, validator.curve[-1].psnr, model, params)

    steps = validator.begin(start, cfg.steps, 0, render)
    offer_validation()
    result.contact_probability = contact_draw_probability(
        validator.train_frames, contact, cfg.contact_fraction, cfg.max_contact_emphasis
    )

    def train_step(step: int) -> tuple[Tensor, dict[str, Tensor], int]:
        frame = sample_frame(gen, validator.train_frames, contact, result.contact_probability)
        camera = int(torch.randint(views.num_cameras, (1,), generator=gen, device="cpu"))
        _set_learning_rates(optimizer, cfg, step)
        t0 = time.perf_counter()
        g = model(*inputs(frame), gen)
        t1 = time.perf_counter()
        out = rasterize(g, views, camera, cfg.backend)
        t2 = time.perf_counter()
        gt, pred = views.target_and_render(out.rgb, frame, camera)
        terms = _loss_terms(pred, gt, labels[frame, camera].numpy(), g, out.radii > 0, cfg, lpips)
        loss = (
            reconstruction_loss(terms, cfg.lambda_dssim, cfg.scale_weight, cfg.position_weight)
            + cfg.patch_weight * terms["patch"]
        )
        t3 = time.perf_counter()
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if params is not None:
            params.step(frame, validator.train_frames)
        t4 = time.perf_counter()
        for key, seconds in (("model", t1 - t0), ("render", t2 - t1), ("loss", t3 - t2), ("backward", t4 - t3)):
            result.seconds[key] += seconds
        result.interaction_evaluations += g.interaction_evaluations
        result.interaction_steps += int(g.interaction_evaluations > 0)
        return loss, terms, g.interaction_evaluations

    def log_row(step: int, outcome: tuple[Tensor, dict[str, Tensor], int]) -> DynamicLogRow:
        loss, terms, interaction_evaluations = outcome
        return DynamicLogRow(
            step,
            loss.item(),
            **loss_values(terms, (*LOSS_TERMS, "patch")),
            interaction_evaluations=interaction_evaluations,
        )

    def checkpoint(step: int) -> None:
        assert ckpt_path is not None
        save_checkpoint(
            ckpt_path,
            {
                **loop_state(step, model, optimizer, gen, result.log, validator),
                "interaction": (result.interaction_evaluations, result.interaction_steps),
                "best": best.state() if best is not None else None,
                "params": params.state() if params is not None else None,
            },
        )

    run_steps(
        progress(steps),
        train_step,
        validator,
        render,
        result.log,
        log_row,
        cfg.log_every,
        checkpoint if ckpt_path is not None else None,
        cfg.checkpoint_every,
        after_validation=offer_validation,
        loss_of=lambda outcome: outcome[0],
        checkpoint_file=ckpt_path,
    )
    if best is not None:
        best.restore(model, params)
        result.selection = select(
            model,
            best,
            validator.end,
            validator.curve[-1].psnr,
            lambda: validator.measure(render),
            cfg.selection.margin_db,
            lambda module: module != "interaction" or bool(contact[validator.frames].any()),
        )
    return result


_CHECKPOINT_KEYS = ("step", "model", "optimizer", "rng", "log", "interaction", "validation", "best", "params")


def _loss_terms(
    pred: Tensor,
    gt: Tensor,
    labels: np.ndarray,
    g: DynamicFrame,
    visible: Tensor,
    cfg: DynamicTrainConfig,
    lpips: LPIPS | None,
) -> dict[str, Tensor]:
    """The terms of the paper's loss for one rendered crop (pred, gt: (S, S, 3); labels: (S, S))."""
    terms = reconstruction_terms(pred, gt, g.local_scales, g.local_means, visible, cfg.eps_s, cfg.eps_mu)
    if cfg.patch_weight > 0:
        if lpips is None:
            raise ValueError("L_patch (cfg.patch_weight > 0) needs the LPIPS network")
        terms["patch"] = patch_perceptual_loss(pred, gt, patch_boxes(labels), lpips, cfg.patch_min_size)
    else:
        terms["patch"] = pred.sum() * 0.0
    return terms
