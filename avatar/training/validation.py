"""Validation during training: a quality curve on withheld training frames, and a stop when it goes flat.

The held-out camera and the held-out motion are the test splits, and nothing is tuned on them. Validation
therefore withholds ``frames`` frames of the *training* sequence (:func:`withheld_frames`: evenly spaced,
never frame 0, the canonical frame whose images also seed the warm-up's colours) and renders them from the
*training* cameras; training never draws a withheld frame (:meth:`Validator.sample_frame`).

A validation renders those F x C images without gradients, with the renderer and backend of training, and
records the mean per-image PSNR of the full image (as stage ``evaluate`` averages it), the render clamped
to [0, 1], and with ``lpips`` the mean LPIPS-alex (``evaluate``'s metric) of the same images. LPIPS is off by
default: at ``draft`` (4 frames, 7 cameras, 128 px) it makes a warm-up validation 1.6 times as costly
(docs/how-to/quality-during-training.md) and the stop rule needs only PSNR; choosing a loss weight that trades
PSNR against perceptual quality on training views needs it (``benchmarks/bench_patch_weight.py``).

The curve has a point at the step training starts from (the starting model), every ``every`` steps, and at
the step it ends. The stop rule (:func:`is_flat`) looks at the points from ``stop_from`` on, the step after
which the loop's own schedule no longer changes the model in jumps (the warm-up's density control, whose
opacity resets pull the PSNR down for a while): it stops when the best PSNR so far has grown by less than
``min_gain_db`` over the last ``window`` validations. Stopping only ends the loop: schedules stay defined
over the planned steps. :meth:`Validator.state` goes into the loop's checkpoint, so a resumed run continues
the curve and takes the same decisions.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from avatar.geometry.views import ViewSet
from avatar.metrics import psnr
from avatar.metrics.evaluation import default_lpips

log = logging.getLogger(__name__)

Render = Callable[[int], Tensor]
"""``render(frame)``: the model's (C, S, S, 3) images of training frame ``frame`` from the C training cameras
(a function of the frame, so that a model is posed once per frame)."""


@dataclass(frozen=True)
class FlatStop:
    """When to stop: the best PSNR gained less than ``min_gain_db`` over the last ``window`` validations."""

    enabled: bool = False
    min_gain_db: float = 0.05
    window: int = 3


@dataclass(frozen=True)
class ValidationConfig:
    """``every``: steps between validations (0: none, no frame withheld); ``frames``: frames withheld (0: none,
    as ``every`` = 0; the stages derive it from the capture's size, :func:`withheld_count`); ``lpips``: measure
    LPIPS-alex too."""

    every: int = 0
    frames: int = 4
    lpips: bool = False
    stop_when_flat: FlatStop = field(default_factory=FlatStop)

    @property
    def enabled(self) -> bool:
        """Whether anything is validated: validations are due and frames are withheld for them."""
        return self.every > 0 and self.frames > 0

    def problems(self) -> list[str]:
        """Range problems, one line each, keyed relative to the validation block; empty when it can run."""
        problems = []
        if self.every < 0:
            problems.append(f"every={self.every}: must be >= 0 (steps between validations; 0 = off)")
        if self.frames < 0:
            problems.append(f"frames={self.frames}: must be >= 0 (training frames withheld for validation)")
        stop = self.stop_when_flat
        if stop.window < 1:
            problems.append(f"stop_when_flat.window={stop.window}: must be >= 1 (validations)")
        if not stop.min_gain_db >= 0.0:  # also refuses NaN
            problems.append(f"stop_when_flat.min_gain_db={stop.min_gain_db:g}: must be >= 0 (dB)")
        return problems


@dataclass
class CurvePoint:
    """One validation: after ``step`` steps and ``wall_s`` seconds of training (validation excluded); ``lpips``
    NaN when not measured."""

    step: int
    wall_s: float
    psnr: float
    lpips: float = math.nan


def withheld_frames(num_frames: int, count: int) -> np.ndarray:
    """(count,) int64: ``count`` of ``num_frames`` frames, evenly spaced and never frame 0.

    Frame ``round((i + 1) T / (count + 1))`` for ``i < count``: distinct, in 1 .. T - 1 whenever
    ``count < T``. ``ValueError`` when no training frame would be left.
    """
    if not 0 < count < num_frames:
        raise ValueError(
            f"cannot withhold {count} of {num_frames} training frames for validation: at least one "
            f"must stay for training (lower validation.frames)"
        )
    return np.floor((np.arange(1, count + 1) * num_frames / (count + 1)) + 0.5).astype(np.int64)


def withheld_count(num_frames: int, fraction: float, min_train_frames: int) -> int:
    """How many of ``num_frames`` training frames validation withholds: ``ceil(fraction T)``, as far as at least
    ``min_train_frames`` stay for training (0 when not even one can be withheld).

    ``fraction`` 0.15 withholds 4 of 24, 2 of 8 and 1 of 5 frames; with ``min_train_frames`` 4, none of 4.
    """
    if not 0.0 < fraction < 1.0:  # also refuses NaN
        raise ValueError(f"validation fraction {fraction}: must lie strictly between 0 and 1")
    wanted = math.ceil(fraction * num_frames - 1e-9)  # 1e-9: 0.25 * 8 is 2, not 3, whatever the rounding
    return max(0, min(wanted, num_frames - min_train_frames))


def draw_frame(gen: torch.Generator, frames: np.ndarray) -> int:
    """One of ``frames`` (K,) drawn uniformly with one ``randint`` of ``gen``: over ``arange(T)`` the very
    draw the loops made before validation existed, so runs without it are unchanged."""
    return int(frames[int(torch.randint(len(frames), (1,), generator=gen, device="cpu"))])


def is_flat(psnrs: Sequence[float], window: int, min_gain_db: float) -> bool:
    """Whether the best PSNR so far grew by less than ``min_gain_db`` over the last ``window`` validations.

    Args:
        psnrs: the curve (dB), oldest first. Fewer than ``window + 1`` points are never flat: the best
            before the window is the reference. NaN points are skipped (the best ignores them).
    """
    if len(psnrs) <= window:
        return False
    best = np.fmax.accumulate(np.asarray(psnrs, dtype=np.float64))
    return bool(best[-1] - best[-1 - window] < min_gain_db)  # NaN (nothing finite yet): False


class Validator:
    """Validation of one training run: the withheld frames, the curve, the stop decision, the timing.

    The caller builds it (the frames it withholds are known from then on) and passes it to a training loop,
    which calls :meth:`begin`, :meth:`sample_frame` and :meth:`after_step` and keeps :meth:`state` in its
    checkpoints; afterwards the caller reads :meth:`table` and :meth:`metrics`.

    Args:
        cfg: the stage's validation block.
        views: the training sequence (its ground truth; the withheld frames are taken from it).
        limit: see ``limit`` below.

    Attributes:
        frames: (F,) int64 withheld frames (empty when validation is off).
        limit: end training after this step whatever the plan (None: the plan's steps), with the schedules
            still defined over the planned steps: a retrain on every frame runs the validated run's schedule
            to the step that run chose.
        train_frames: (T - F,) int64 frames training draws from.
        planned_steps, stop_from: the loop's steps, and the first step the stop rule looks at (set by
            :meth:`begin`).
        curve: the points so far.
        stopped_at: the step the rule stopped at, or None.
        train_s, validation_s: seconds spent training (from :meth:`begin` on, validation excluded) and
            validating, including those of the run a checkpoint resumed.
    """

    def __init__(self, cfg: ValidationConfig, views: ViewSet, limit: int | None = None) -> None:
        self.cfg, self.views = cfg, views
        self.planned_steps, self.stop_from = 0, 0
        self.limit = limit
        self.frames = withheld_frames(views.num_frames, cfg.frames) if cfg.enabled else np.zeros(0, dtype=np.int64)
        self.train_frames = np.setdiff1d(np.arange(views.num_frames), self.frames)
        self.curve: list[CurvePoint] = []
        self.stopped_at: int | None = None
        self.resumed_from = 0  # the step a checkpoint resumed after (0: started from scratch)
        self.train_s = 0.0
        self.validation_s = 0.0
        self._clock = time.perf_counter()

    @property
    def end(self) -> int:
        """The step training ends at: where it stopped, else the planned steps (at most ``limit``)."""
        if self.stopped_at is not None:
            return self.stopped_at
        return self.planned_steps if self.limit is None else min(self.limit, self.planned_steps)

    def sample_frame(self, gen: torch.Generator) -> int:
        """A training frame drawn uniformly (:func:`draw_frame`)."""
        return draw_frame(gen, self.train_frames)

    def begin(self, start: int, planned_steps: int, stop_from: int, render: Render) -> range:
        """Start (or resume after step ``start``) a loop of ``planned_steps`` steps whose stop rule looks at
        the steps from ``stop_from`` on: start the clock, validate the starting model when the curve has no
        point yet. Returns the steps left to run."""
        self.planned_steps, self.stop_from = planned_steps, stop_from
        self.resumed_from = start
        if start:
            log.info("resumed from a checkpoint after step %d of %d", start, planned_steps)
        self._clock = time.perf_counter()
        self.after_step(start, render)
        return range(start + 1, self.end + 1)

    def after_step(self, step: int, render: Render) -> bool:
        """Validate after optimiser step ``step`` when one is due, and apply the stop rule; True to stop."""
        if not self._due(step):
            return False
        self._lap()
        with torch.no_grad():
            self.curve.append(CurvePoint(step, self.train_s, *self._measure(render)))
        if self.cfg.stop_when_flat.enabled and step < self.planned_steps and self._flat():
            self.stopped_at = step
        now = time.perf_counter()
        self.validation_s += now - self._clock
        self._clock = now
        return self.stopped_at is not None

    def _due(self, step: int) -> bool:
        if not self.cfg.enabled or (self.curve and self.curve[-1].step >= step):
            return False
        return not self.curve or step % self.cfg.every == 0 or step == self.planned_steps

    def _lap(self) -> None:
        """Add the time since the last mark to ``train_s``."""
        now = time.perf_counter()
        self.train_s += now - self._clock
        self._clock = now

    def measure(self, render: Render) -> float:
        """Mean full-image PSNR (dB) of ``render``'s images of the withheld frames, as a validation point has it
        (no point is added; for comparing variants of the model at one step)."""
        with torch.no_grad():
            return self._measure(render)[0]

    def _measure(self, render: Render) -> tuple[float, float]:
        """Mean full-image PSNR (dB, over the observed pixels) and LPIPS-alex (NaN unless ``cfg.lpips``) over
        the withheld frames and the training cameras; crop padding is left out as in training."""
        pairs = [
            self.views.target_and_render(image, int(t), c)
            for t in self.frames
            for c, image in enumerate(render(int(t)).clamp(0, 1))
        ]
        gt, pred = (torch.stack(images).permute(0, 3, 1, 2) for images in zip(*pairs))  # (F C, 3, S, S)
        observed = torch.stack(
            [self.views.observed(int(t), c) for t in self.frames for c in range(self.views.num_cameras)]
        )  # (F C, S, S)
        lpips = (
            float(default_lpips().to(pred.device)(pred.float(), gt.float(), unit_range=True).mean())
            if self.cfg.lpips
            else math.nan
        )
        return float(psnr(pred, gt, observed).mean()), lpips

    def _flat(self) -> bool:
        stop = self.cfg.stop_when_flat
        return is_flat([p.psnr for p in self.curve if p.step >= self.stop_from], stop.window, stop.min_gain_db)

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps (plain numbers and lists) to resume the curve and the stop decision."""
        self._lap()
        return {
            "curve": [asdict(p) for p in self.curve],
            "stopped_at": self.stopped_at,
            "train_s": self.train_s,
            "validation_s": self.validation_s,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`state`."""
        self.curve = [CurvePoint(**p) for p in state["curve"]]
        self.stopped_at = state["stopped_at"]
        self.train_s, self.validation_s = float(state["train_s"]), float(state["validation_s"])

    def table(self) -> dict[str, np.ndarray]:
        """The curve as the columns of ``curve.parquet`` (``data_schemas.curve.CURVE``)."""
        return {
            "step": np.array([p.step for p in self.curve], dtype=np.int64),
            "wall_s": np.array([p.wall_s for p in self.curve], dtype=np.float64),
            "psnr": np.array([p.psnr for p in self.curve], dtype=np.float64),
            "lpips": np.array([p.lpips for p in self.curve], dtype=np.float64),
        }

    def metrics(self) -> dict[str, float | int | bool]:
        """Manifest metrics: ``stopped_at_step`` (steps run), ``planned_steps``, ``early_stopped``,
        ``validation_s``, ``resumed_from_step`` (the checkpoint's step a killed run was resumed from, else 0);
        with a curve ``validation_psnr`` (its last point) and with LPIPS ``validation_lpips``; when stopped early
        ``time_saved_s``, the steps not run times the mean training step time."""
        out: dict[str, float | int | bool] = {
            "stopped_at_step": self.end,
            "planned_steps": self.planned_steps,
            "early_stopped": self.stopped_at is not None,
            "validation_s": self.validation_s,
            "resumed_from_step": self.resumed_from,
        }
        if self.curve:
            out["validation_psnr"] = self.curve[-1].psnr
            if self.cfg.lpips:
                out["validation_lpips"] = self.curve[-1].lpips
        if self.stopped_at is not None:
            out["time_saved_s"] = (self.planned_steps - self.end) * self.train_s / max(self.end, 1)
        return out
