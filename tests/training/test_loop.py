"""avatar.training.loop.run_steps: the order of a step's parts, the log and checkpoint cadence, the stop."""

from __future__ import annotations

from typing import Any, cast

import torch

from avatar.training.loop import run_steps
from avatar.training.validation import Validator


class Recorder:
    """A validator that stops at ``stop_at`` and records, with the loop's other calls, what ran in which order."""

    def __init__(self, end: int, stop_at: int | None = None) -> None:
        self.end, self.stop_at, self.calls = end, stop_at, []

    def after_step(self, step: int, render: Any) -> bool:
        self.calls.append(("validate", step))
        return step == self.stop_at


def run(steps: range, validator: Recorder, log_every: int, checkpoint_every: int, with_checkpoint: bool = True):
    log: list[tuple[int, int]] = []
    run_steps(
        steps,
        lambda step: validator.calls.append(("step", step)) or step * 10,
        cast(Validator, validator),
        lambda frame: torch.zeros(1),
        log,
        lambda step, outcome: (step, outcome),
        log_every,
        (lambda step: validator.calls.append(("checkpoint", step))) if with_checkpoint else None,
        checkpoint_every,
        after_validation=lambda: validator.calls.append(("offer", -1)),
    )
    return log


def test_each_step_trains_then_validates_then_offers_logs_and_checkpoints_in_that_order() -> None:
    validator = Recorder(end=4)
    log = run(range(1, 5), validator, log_every=2, checkpoint_every=3)
    assert log == [(2, 20), (4, 40)]  # every 2nd step and the validator's last
    assert validator.calls[:4] == [("step", 1), ("validate", 1), ("offer", -1), ("step", 2)]
    assert ("checkpoint", 3) in validator.calls and ("checkpoint", 2) not in validator.calls
    assert validator.calls.index(("checkpoint", 3)) == validator.calls.index(("offer", -1), 8) + 1


def test_the_last_step_is_logged_and_the_stop_ends_the_loop_after_its_step() -> None:
    validator = Recorder(end=3, stop_at=3)
    log = run(range(1, 10), validator, log_every=100, checkpoint_every=0)
    assert log == [(3, 30)]  # the validator's last step, though not a multiple of log_every
    assert ("step", 4) not in validator.calls
    assert not any(call[0] == "checkpoint" for call in validator.calls)  # checkpoint_every=0: never


def test_without_a_checkpoint_function_nothing_is_saved() -> None:
    validator = Recorder(end=6)
    run(range(1, 7), validator, log_every=1, checkpoint_every=1, with_checkpoint=False)
    assert not any(call[0] == "checkpoint" for call in validator.calls)
