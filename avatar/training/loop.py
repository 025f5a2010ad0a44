"""The loop every training recipe runs (the warm-up, stage two, SplattingAvatar's): a step, then validation, the
log every ``log_every`` steps and at the validator's end, a checkpoint every ``checkpoint_every`` steps, and the
stop the validation calls. A recipe gives what is its own: the step (drawing a frame and a camera, the forward
pass, the losses, the updates), the log row, and what a checkpoint holds. A run whose loss or parameters stop being
finite ends with :class:`TrainingDiverged`, and its checkpoints are deleted: resumed, they would diverge again."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, TypeVar

import torch
from torch import Tensor, nn

from avatar.training.checkpoint import discard_checkpoint
from avatar.training.validation import Validator

Outcome = TypeVar("Outcome")
Row = TypeVar("Row")


class TrainingDiverged(FloatingPointError):
    """A training run's loss or parameters stopped being finite (too high a learning rate, most often).

    Attributes:
        step: the step at which it was found (the loss is read every ``log_every`` steps, before every checkpoint and
            at the run's last step).
        what: what was not finite, e.g. ``the loss is nan``.
    """

    def __init__(self, step: int, what: str, advice: str = "") -> None:
        super().__init__(f"training diverged at step {step}: {what}" + (f"; {advice}" if advice else ""))
        self.step, self.what = step, what

    def advised(self, recipe: str, rates: Mapping[str, float]) -> TrainingDiverged:
        """The same divergence, saying which ``recipe`` (``the warm-up``) diverged and which learning rates
        (config key -> value) to lower, and that the run's checkpoints are gone."""
        keys = ", ".join(f"{key}={value:g}" for key, value in rates.items())
        advice = (
            f"{recipe} cannot go on from here; lower its learning rates (tenfold, say): {keys}. "
            "Its checkpoints were deleted (resumed, the run would diverge again), so the next run starts over"
        )
        return TrainingDiverged(self.step, self.what, advice)


def learning_rates(prefix: str, config: Any, start: str = "lr_", exclude: Sequence[str] = ()) -> dict[str, float]:
    """``<prefix>.<name>`` -> value of the fields of a config dataclass whose names begin with ``start`` (its learning
    rates), but ``exclude``: the keys :meth:`TrainingDiverged.advised` names."""
    return {
        f"{prefix}.{f.name}": float(getattr(config, f.name))
        for f in fields(config)
        if f.name.startswith(start) and f.name not in exclude
    }


@contextmanager
def advising(recipe: str, rates: Mapping[str, float]) -> Iterator[None]:
    """The block, whose :class:`TrainingDiverged` says which ``recipe`` diverged and the ``rates`` to lower
    (:meth:`TrainingDiverged.advised`)."""
    try:
        yield
    except TrainingDiverged as exc:
        raise exc.advised(recipe, rates) from None


def run_steps(
    steps: Iterable[int],
    train_step: Callable[[int], Outcome],
    validator: Validator,
    render: Callable[[int], Tensor],
    log: list[Row],
    log_row: Callable[[int, Outcome], Row],
    log_every: int,
    checkpoint: Callable[[int], None] | None = None,
    checkpoint_every: int = 0,
    after_validation: Callable[[], None] | None = None,
    *,
    loss_of: Callable[[Outcome], Tensor],
    checkpoint_file: Path | None = None,
) -> None:
    """Run ``train_step`` for each of ``steps`` (already wrapped in a progress bar where wanted).

    After each step the validator measures when it is due (``render(frame)``: (C, S, S, 3) renders of a withheld
    frame) and may call a stop; ``after_validation`` runs next (stage two offers the validated state to its
    selection there). ``log_row(step, outcome)`` is appended to ``log`` every ``log_every`` steps and at the
    validator's last step, and ``checkpoint(step)`` runs every ``checkpoint_every`` steps (never where it is None or
    ``checkpoint_every`` is 0). The loop ends after the step at which the validation stopped.

    The step's loss (``loss_of(outcome)``) is read on the host where the log or a checkpoint reads the step anyway
    and at the last step; where it is not finite the run raises :class:`TrainingDiverged` and deletes
    ``checkpoint_file`` (where ``checkpoint`` saves) with its previous version, so no later run resumes from them.
    """
    last: tuple[int, Outcome] | None = None
    with _discarded_when_diverged(checkpoint_file):
        for step in steps:
            outcome = train_step(step)
            last = (step, outcome)
            logged = step % log_every == 0 or step == validator.end
            saved = checkpoint is not None and checkpoint_every > 0 and step % checkpoint_every == 0
            if logged or saved:
                _ensure_finite(loss_of(outcome), step)
            stop = validator.after_step(step, render)
            if after_validation is not None:
                after_validation()
            if logged:
                log.append(log_row(step, outcome))
            if saved and checkpoint is not None:
                checkpoint(step)
            if stop:
                break
        if last is not None:
            _ensure_finite(loss_of(last[1]), last[0])


@contextmanager
def _discarded_when_diverged(checkpoint_file: Path | None) -> Iterator[None]:
    """Delete ``checkpoint_file`` and its previous version when the block raises :class:`TrainingDiverged`."""
    try:
        yield
    except TrainingDiverged:
        if checkpoint_file is not None:
            discard_checkpoint(checkpoint_file)
        raise


def _ensure_finite(loss: Tensor, step: int) -> None:
    """:class:`TrainingDiverged` unless ``loss`` (a scalar) is finite (reads it on the host)."""
    value = float(loss.detach())
    if not math.isfinite(value):
        raise TrainingDiverged(step, f"the loss is {value}")


def loss_values(terms: Mapping[str, Tensor], names: Sequence[str]) -> dict[str, float]:
    """The scalar loss terms ``names`` of a step as floats, for its log row."""
    return {name: terms[name].item() for name in names}


def loop_state(
    step: int,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    log: Sequence[Any],
    validator: Validator,
) -> dict[str, Any]:
    """What every recipe's checkpoint holds to resume the loop bit for bit: the step, the model's and the optimiser's
    state, the sampler's generator, the log so far (dataclass rows) and the validation's state; a recipe adds its
    own (density control, refined parameters, the selection). :class:`TrainingDiverged` where a parameter of the
    model is not finite: such a state is never saved."""
    bad = [
        name for name, value in model.state_dict().items() if value.is_floating_point() and not value.isfinite().all()
    ]
    if bad:
        raise TrainingDiverged(step, f"the model's {', '.join(bad[:3])} {'is' if len(bad) == 1 else 'are'} not finite")
    return {
        "step": step,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "rng": generator.get_state(),
        "log": [asdict(row) for row in log],
        "validation": validator.state(),
    }
