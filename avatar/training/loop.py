"""The loop every training recipe runs (the warm-up, stage two, SplattingAvatar's): a step, then validation, the
log every ``log_every`` steps and at the validator's end, a checkpoint every ``checkpoint_every`` steps, and the
stop the validation calls. A recipe gives what is its own: the step (drawing a frame and a camera, the forward
pass, the losses, the updates), the log row, and what a checkpoint holds."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict
from typing import Any, TypeVar

import torch
from torch import Tensor, nn

from avatar.training.validation import Validator

Outcome = TypeVar("Outcome")
Row = TypeVar("Row")


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
) -> None:
    """Run ``train_step`` for each of ``steps`` (already wrapped in a progress bar where wanted).

    After each step the validator measures when it is due (``render(frame)``: (C, S, S, 3) renders of a withheld
    frame) and may call a stop; ``after_validation`` runs next (stage two offers the validated state to its
    selection there). ``log_row(step, outcome)`` is appended to ``log`` every ``log_every`` steps and at the
    validator's last step, and ``checkpoint(step)`` runs every ``checkpoint_every`` steps (never where it is None or
    ``checkpoint_every`` is 0). The loop ends after the step at which the validation stopped.
    """
    for step in steps:
        outcome = train_step(step)
        stop = validator.after_step(step, render)
        if after_validation is not None:
            after_validation()
        if step % log_every == 0 or step == validator.end:
            log.append(log_row(step, outcome))
        if checkpoint is not None and checkpoint_every and step % checkpoint_every == 0:
            checkpoint(step)
        if stop:
            break


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
    own (density control, refined parameters, the selection)."""
    return {
        "step": step,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "rng": generator.get_state(),
        "log": [asdict(row) for row in log],
        "validation": validator.state(),
    }
