"""A motion tracked by a trained avatar held frozen: each frame's FLAME/MANO parameters refined so that the
avatar's renders match that frame's images from a set of cameras.

Avatar papers with test motions of their own (InstantAvatar, ARAH, HumanNeRF) refine each test frame's pose with
the trained model frozen before they measure: a tracker's error on a motion the avatar never saw is not the
avatar's, and left in place it dominates every image metric. Here each frame of the motion starts from the
tracker's parameters and an Adam of its own (:class:`~avatar.training.frame_params.FrameAdam`, its rates decayed
geometrically over the steps) moves that frame's rotations, translations, articulation and expression
(:data:`~avatar.training.frame_params.REFINED_COLUMNS`; the shapes stay) to lower the L1 error between the
avatar's renders and the crops of every camera of the given views, on the pixels the cameras saw. A part that
none of those views shows in a frame (fewer than :data:`MIN_VISIBLE_PIXELS` pixels of its label) keeps the
tracker's parameters there. The face's contact offsets (the pbd stage's, simulated on the tracker's meshes) are
added to the refined face unchanged, as in training.

The gradient reaches the parameters through the posed meshes alone. The avatar's networks (InteractAvatar's H, I and
PointNet++) read the frame's conditioning, computed from the current parameters without gradient
(:meth:`~avatar.training.frame_params.FrameParams.posed`): they run forward only, but at every step, since their
inputs follow the parameters as these move. What they compute from inputs that no frame changes (a Gaussian's
position code and point features times their first layers) is computed once, by the pose function the caller passes
(:func:`avatar.representations.frame_pose`).

Which cameras it may look at is the caller's choice and the protocol's core: a frame tuned on a camera and scored
on the same camera measures the refinement, not the avatar (see ``stages.evaluate``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from avatar.device import host
from avatar.dynamic.conditioning import FrameConditioning
from avatar.geometry.views import FACE_LABEL, HAND_LABEL, ViewSet
from avatar.render.gaussians.world import WorldGaussians
from avatar.templates import TemplateModel
from avatar.training.frame_params import FrameParams, ParamLearningRates
from avatar.training.rendering import rasterize
from data_schemas.tables import SchemaError

#: a part counts as seen in a frame when its label covers at least this many crop pixels in one of the views
MIN_VISIBLE_PIXELS = 4
#: part -> the prefix of its params.parquet columns and its crop label
PARTS: dict[str, tuple[str, int]] = {"face": ("flame_", FACE_LABEL), "hand": ("mano_", HAND_LABEL)}
#: frames refined together by default (:func:`track_with_avatar`): a draft capture's held-out motion (12) at once
BATCH_FRAMES = 12

#: The frozen avatar of one frame: (the frame's conditioning, its posed vertices (V, 3)) -> world Gaussians.
PoseFrame = Callable[[FrameConditioning, Tensor], WorldGaussians]


@dataclass
class AvatarTrackingConfig:
    """Settings of :func:`track_with_avatar` (``stage.evaluate.tracking``). Rates are Adam's per step at the first
    step, in the parameters' own units, decayed geometrically to ``final_rate`` times that at the last."""

    # chosen on the train motion's training views (benchmarks/bench_test_tracking.py rates; docs: tracking-refinement)
    steps: int = 40  # Adam steps per frame (each renders every tuning camera of the frame once)
    lr_rotation: float = 0.008  # of the global rotations (rad)
    lr_pose: float = 0.008  # of the neck, jaw, eye and finger poses (rad)
    lr_translation_mm: float = 1.0  # of the translations (mm)
    lr_expression: float = 0.04  # of the expression coefficients
    final_rate: float = 0.1  # the rates at the last step, as a multiple of the first step's

    def rates(self) -> ParamLearningRates:
        """The first step's rates in :class:`ParamLearningRates`' units (radians, metres, expression units)."""
        return ParamLearningRates(
            rotation=self.lr_rotation,
            pose=self.lr_pose,
            translation=self.lr_translation_mm * 1e-3,
            expression=self.lr_expression,
        )

    def problems(self) -> list[str]:
        """Range problems, one line each, keyed relative to the block; empty when it can run."""
        out = [] if self.steps >= 0 else [f"steps={self.steps}: must be >= 0 (0: the tracker's parameters as they are)"]
        out += [
            f"{f.name}={getattr(self, f.name):g}: must be a finite rate >= 0 (0 holds the group)"
            for f in fields(self)
            if f.name.startswith("lr_") and not (math.isfinite(getattr(self, f.name)) and getattr(self, f.name) >= 0)
        ]
        if not (0 < self.final_rate <= 1):
            out.append(f"final_rate={self.final_rate:g}: must be in (0, 1] (1: no decay)")
        return out


@dataclass
class TrackedMotion:
    """What :func:`track_with_avatar` returns.

    Attributes:
        params: the refined params.parquet columns, (T, D) float32 each (every column, the shapes as given).
        loss_before: (T,) the L1 error of each frame's renders with the tracker's parameters.
        loss_after: (T,) and with the refined ones (the last step's parameters, rendered again).
        held: part -> (T,) bool, the frames in which that part kept the tracker's parameters (not seen).
    """

    params: dict[str, np.ndarray]
    loss_before: np.ndarray
    loss_after: np.ndarray
    held: dict[str, np.ndarray]


def track_with_avatar(
    pose: PoseFrame,
    params: Mapping[str, np.ndarray],
    head: TemplateModel,
    hand: TemplateModel,
    face_offsets: Tensor | None,
    views: ViewSet,
    config: AvatarTrackingConfig,
    backend: str = "auto",
    progress: Callable[[Iterable[int]], Iterable[int]] = lambda steps: steps,
    batch_frames: int = BATCH_FRAMES,
) -> TrackedMotion:
    """Refine every frame of a motion with the avatar ``pose`` frozen, from ``views`` alone.

    The frames are independent problems (each its own Adam; the avatar frozen), refined ``batch_frames`` at a time
    in lockstep: each step poses the batch's meshes with one run of the template layers, renders every frame, and
    takes one backward pass through the sum of the frames' losses, whose gradient in a frame's parameters is that
    frame's own loss's.

    Args:
        pose: the trained avatar of one frame (its parameters must not require gradients: nothing of it moves), as
            :func:`avatar.representations.frame_pose` gives it.
        params: the tracker's params.parquet columns, T rows each; T must equal ``views.num_frames``.
        head, hand: the templates the avatar was trained on.
        face_offsets: (T, V_face, 3) world-frame contact offsets added to the posed face (None: none).
        views: the crops the refinement may look at: every camera of it is used, and no other; the parameters
            are refined on their device (the avatar's).
        config: steps and rates.
        backend: the rasterizer.
        progress: wraps each batch's loop over the steps (a progress bar).
        batch_frames: frames refined together (the memory of their renders' and poses' backward passes grows with
            it); the parameters found do not depend on it, to rounding.
    """
    num_frames = len(next(iter(params.values())))
    if num_frames != views.num_frames:
        raise ValueError(f"{num_frames} frames of parameters but {views.num_frames} of images")
    frames = FrameParams(params, head, hand, face_offsets, config.rates(), device=views.images.device)
    held = {part: ~_seen(views, label) for part, (_, label) in PARTS.items()}
    before, after = np.zeros(num_frames), np.zeros(num_frames)
    decay = config.final_rate ** (1 / max(config.steps - 1, 1))
    size = max(batch_frames, 1)
    for start in range(0, num_frames, size):
        batch = slice(start, min(start + size, num_frames))
        for step in progress(range(config.steps)):
            losses = _losses(pose, frames, views, batch, backend)
            if step == 0:  # the tracker's parameters
                before[batch] = host(losses)
            losses.sum().backward()
            frames.optimizer.step(batch, lr_scale=decay**step)
        with torch.no_grad():
            if config.steps == 0:
                before[batch] = host(_losses(pose, frames, views, batch, backend))
            _hold(frames, batch, held)
            after[batch] = host(_losses(pose, frames, views, batch, backend))
    return TrackedMotion(frames.arrays(), before, after, held)


def _losses(pose: PoseFrame, frames: FrameParams, views: ViewSet, batch: slice, backend: str) -> Tensor:
    """(B,): the mean L1 error of each frame of ``batch``'s renders over every camera of ``views`` (observed pixels
    only)."""
    vertices, cond = frames.posed(batch)
    losses = []
    for i, t in enumerate(range(batch.start, batch.stop)):
        gaussians = pose(cond.frame(i), vertices[i])
        total = torch.zeros((), device=views.images.device)
        for c in range(views.num_cameras):
            gt, render = views.target_and_render(rasterize(gaussians, views, c, backend).rgb, t, c)
            total = total + (render - gt).abs().mean()
        losses.append(total / views.num_cameras)
    return torch.stack(losses)


def _seen(views: ViewSet, label: int) -> np.ndarray:
    """(T,) bool: frames in which some camera of ``views`` shows at least :data:`MIN_VISIBLE_PIXELS` of ``label``."""
    counts = (views.labels == label).flatten(2).sum(-1)  # (T, C)
    return host((counts >= MIN_VISIBLE_PIXELS).any(1))


def _hold(frames: FrameParams, batch: slice, held: Mapping[str, np.ndarray]) -> None:
    """Put the tracker's parameters back into the frames of ``batch`` in which ``held`` (part -> (T,) bool) holds
    that part."""
    index = np.arange(frames.num_frames)[batch]
    with torch.no_grad():
        for part, (prefix, _) in PARTS.items():
            rows = torch.as_tensor(index[held[part][batch]], device=frames.face_offsets.device)
            for column, values in frames.rows.items():  # the refined columns (REFINED_COLUMNS)
                if column.startswith(prefix) and len(rows):
                    values[rows] = frames.start[column][rows]


def untracked_reason(camera_ids: Sequence[str]) -> str | None:
    """Why no choice of tuning cameras among the training cameras ``camera_ids`` can track the held-out motion and
    score it on others: fewer than two (a monocular capture). ``None`` where some choice can. Evaluate skips the
    avatar-tracked split for this reason, whatever ``stage.evaluate.tuning_cameras`` names, and says so."""
    if len(camera_ids) >= 2:
        return None
    named = f"one training camera ({camera_ids[0]})" if camera_ids else "no training camera"
    return f"{named}: none is left to score the motion the avatar tracked on it"


def tracking_cameras(setting: Any, camera_ids: list[str]) -> tuple[list[str], list[str]]:
    """(tuning, scoring) training cameras of ``stage.evaluate.tuning_cameras`` = ``setting``: ``auto`` takes every
    other training camera by sorted id (the 1st, 3rd, ...) to tune and leaves the rest to score; a list names the
    tuning ones. Both must be non-empty (SchemaError naming the key otherwise; with fewer than two training cameras
    :func:`untracked_reason`'s)."""
    why = untracked_reason(camera_ids)
    if why is not None:
        raise SchemaError(f"stage.evaluate.test_tracking=avatar: {why}; set stage.evaluate.test_tracking=tracker")
    ordered = sorted(camera_ids)
    tuning = ordered[::2] if setting == "auto" else [str(c) for c in setting]
    unknown = sorted(set(tuning) - set(ordered))
    if unknown:
        raise SchemaError(
            f"stage.evaluate.tuning_cameras: {unknown} are not training cameras of this capture ({ordered})"
        )
    scoring = [c for c in ordered if c not in tuning]
    if not scoring:
        raise SchemaError(
            f"stage.evaluate.tuning_cameras={list(tuning)}: leaves no training camera to score the avatar-tracked "
            "motion on; name fewer, or set stage.evaluate.test_tracking=tracker"
        )
    return tuning, scoring
