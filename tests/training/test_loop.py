"""avatar.training.loop.run_steps: the order of a step's parts, the log and checkpoint cadence, the stop, and the end
of a run whose loss stops being finite."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import pytest
import torch

from avatar.training.checkpoint import previous_path, save_checkpoint
from avatar.training.loop import TrainingDiverged, loop_state, run_steps
from avatar.training.validation import Validator


class Recorder:
    """A validator that stops at ``stop_at`` and records, with the loop's other calls, what ran in which order."""

    def __init__(self, end: int, stop_at: int | None = None) -> None:
        self.end, self.stop_at, self.calls = end, stop_at, []

    def after_step(self, step: int, render: Any) -> bool:
        self.calls.append(("validate", step))
        return step == self.stop_at


def run(
    steps: range,
    validator: Recorder,
    log_every: int,
    checkpoint_every: int,
    with_checkpoint: bool = True,
    nan_from: int | None = None,
    checkpoint_file: Path | None = None,
):
    """The loop over ``steps`` whose step ``s`` has the outcome (loss) ``10 s``, NaN from step ``nan_from`` on."""
    log: list[tuple[int, float]] = []
    run_steps(
        steps,
        lambda step: (
            validator.calls.append(("step", step))
            or (step * 10.0 if nan_from is None or step < nan_from else float("nan"))
        ),
        cast(Validator, validator),
        lambda frame: torch.zeros(1),
        log,
        lambda step, outcome: (step, outcome),
        log_every,
        (lambda step: validator.calls.append(("checkpoint", step))) if with_checkpoint else None,
        checkpoint_every,
        after_validation=lambda: validator.calls.append(("offer", -1)),
        loss_of=torch.tensor,
        checkpoint_file=checkpoint_file,
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


def test_a_loss_that_stops_being_finite_ends_the_run_where_it_is_read_and_deletes_the_checkpoints(
    tmp_path: Path,
) -> None:
    """The loss is read on the host only where the log or a checkpoint reads the step: a NaN from step 3 is found at
    step 4 (logged), before its checkpoint would be saved; the run's checkpoint and its previous one are deleted."""
    checkpoint = tmp_path / "run.pt"
    save_checkpoint(checkpoint, {"step": 1})
    save_checkpoint(checkpoint, {"step": 2})
    assert previous_path(checkpoint).exists()
    validator = Recorder(end=10)
    with pytest.raises(TrainingDiverged, match=r"training diverged at step 4: the loss is nan"):
        run(range(1, 11), validator, log_every=2, checkpoint_every=4, nan_from=3, checkpoint_file=checkpoint)
    assert ("step", 4) in validator.calls and ("checkpoint", 4) not in validator.calls
    assert ("validate", 4) not in validator.calls  # nothing more runs on a diverged model
    assert not checkpoint.exists() and not previous_path(checkpoint).exists()


def test_the_last_step_is_read_too() -> None:
    with pytest.raises(TrainingDiverged, match="at step 5"):
        run(range(1, 6), Recorder(end=9), log_every=100, checkpoint_every=0, nan_from=5)


def test_a_state_with_a_parameter_that_is_not_finite_is_never_saved() -> None:
    model = torch.nn.Linear(2, 1)
    with torch.no_grad():
        model.bias.fill_(float("inf"))
    optimizer = torch.optim.Adam(model.parameters())
    with pytest.raises(TrainingDiverged, match="at step 3: the model's bias is not finite"):
        loop_state(3, model, optimizer, torch.Generator(), [], cast(Validator, Recorder(end=3)))
