"""Keep only what the training views support: stage two's best validation step, and its modules by need.

Stage two validates on training frames it withholds (:mod:`avatar.training.validation`; the warm-up withholds
the same ones, so no model saw them). The rule, fixed before any held-out figure was looked at:

1. **Step.** Of the validated steps, keep the one with the highest validation PSNR; step 0 (the warm-up's
   Gaussians, H and I at zero: GaussianAvatars' model with this method's PBD) is a candidate. Ties keep the
   earlier step, the simpler model.
2. **Modules.** At that step, switch each module off in turn (H: both hand MLPs; then I), and leave it off
   when that lowers the validation PSNR by at most ``margin_db``; a module that does not pay for itself on
   frames it never saw is not kept. Switched off means its output layers are zero, which is exactly a zero
   delta (they start at zero), so the written model renders as if the module had never been built. A module
   is judged only where a withheld frame is one it is for: I, which models contact, only when a withheld frame
   has contact (the ``pbd`` stage's flags). Without one, switching it off changes next to nothing on the
   validation frames (on issue 53's setting (c), not the last digit of the PSNR), which is no evidence that it
   is worth nothing, so it is kept (``judged`` False).

The held-out camera and the held-out motion are never looked at.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from avatar.nets.mlp import DeltaHeads, SharedDeltaHeads
from avatar.training.frame_params import FrameParams

#: a module's name -> the model attributes it consists of (the stage-two networks whose deltas it adds)
MODULES = {"hand_mlp": ("hand_geo", "hand_app"), "interaction": ("interaction",)}


@dataclass(frozen=True)
class SelectionConfig:
    """``enabled``: select (needs validation); ``margin_db``: the validation PSNR a module must be worth."""

    enabled: bool = False
    margin_db: float = 0.05

    def problems(self) -> list[str]:
        """Range problems, one line each, keyed relative to the select block."""
        return [] if self.margin_db >= 0.0 else [f"margin_db={self.margin_db:g}: must be >= 0 (dB)"]


class BestStep:
    """The model state at the best validation point so far (highest PSNR, the earliest on ties).

    Attributes:
        step: the best point's step (-1 before any).
        psnr: its validation PSNR (dB).
        offered: the last step offered (a resumed run does not offer a point twice).
    """

    def __init__(self) -> None:
        self.step, self.psnr, self.offered = -1, float("-inf"), -1
        self._state: dict[str, Tensor] | None = None
        self._params: dict[str, Any] | None = None

    def offer(self, step: int, psnr: float, model: nn.Module, params: FrameParams | None = None) -> None:
        """Keep a copy of ``model``'s state (and of the refined ``params``, if any) if ``psnr`` beats the best
        so far."""
        self.offered = step
        if psnr > self.psnr:
            self.step, self.psnr = step, psnr
            self._state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            self._params = params.state() if params is not None else None

    def restore(self, model: nn.Module, params: FrameParams | None = None) -> None:
        """Load the best state into ``model`` and ``params`` (nothing when no point was offered)."""
        if self._state is not None:
            model.load_state_dict(self._state)
        if params is not None and self._params is not None:
            params.load_state(self._params)

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps to resume the choice bit for bit."""
        return {
            "step": self.step,
            "psnr": self.psnr,
            "offered": self.offered,
            "model": self._state,
            "params": self._params,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.step, self.psnr, self.offered = int(state["step"]), float(state["psnr"]), int(state["offered"])
        self._state, self._params = state["model"], state["params"]


@dataclass
class Selection:
    """What stage two kept, and the validation figures the choice rests on (dB).

    Attributes:
        selected_step: the step whose model was kept; final_step: the step training ended at.
        selected_psnr, final_psnr: validation PSNR at those steps.
        kept: module -> kept (False also for a module the method never built).
        psnr_without: module -> validation PSNR of the selected model with that module switched off (only the
            modules that were built).
        psnr: validation PSNR of what was written (the selected step, less what was switched off).
        judged: module -> whether a withheld frame is one it is for (only the modules that were built); one without
            is kept unjudged.
    """

    selected_step: int
    final_step: int
    selected_psnr: float
    final_psnr: float
    kept: dict[str, bool] = field(default_factory=dict)
    psnr_without: dict[str, float] = field(default_factory=dict)
    psnr: float = float("nan")
    judged: dict[str, bool] = field(default_factory=dict)

    def metrics(self) -> dict[str, float | int | bool]:
        """Manifest metrics: ``selected_step``, ``kept_hand_mlp``, ``kept_interaction`` and the figures."""
        out: dict[str, float | int | bool] = {
            "selected_step": self.selected_step,
            "selection_final_step": self.final_step,
            "selection_selected_psnr": self.selected_psnr,
            "selection_final_psnr": self.final_psnr,
            "selection_psnr": self.psnr,
        }
        out |= {f"kept_{module}": kept for module, kept in self.kept.items()}
        out |= {f"selection_psnr_without_{module}": psnr for module, psnr in self.psnr_without.items()}
        out |= {f"selection_judged_{module}": judged for module, judged in self.judged.items()}
        return out


def module_heads(model: nn.Module, module: str) -> list[DeltaHeads | SharedDeltaHeads]:
    """The built networks of ``module`` (a key of :data:`MODULES`) in ``model`` (empty when not built)."""
    return [net for name in MODULES[module] if (net := getattr(model, name, None)) is not None]


def switch_off(nets: list[DeltaHeads | SharedDeltaHeads]) -> None:
    """Zero the output layers of every head of ``nets``: each then adds exactly a zero delta."""
    with torch.no_grad():
        for net in nets:
            for output in net.output_layers():
                output.weight.zero_()
                output.bias.zero_()


def select(
    model: nn.Module,
    best: BestStep,
    final_step: int,
    final_psnr: float,
    measure: Callable[[], float],
    margin_db: float,
    acts: Callable[[str], bool] = lambda module: True,
) -> Selection:
    """Apply the rule of the module docstring to ``model`` in place.

    Args:
        best: the best validation point of the run (its state is loaded into ``model``).
        final_step, final_psnr: where training ended, and its validation PSNR.
        measure: ``measure()`` -> the validation PSNR (dB) of ``model`` as it is now.
        margin_db: switch a module off when that costs at most this much validation PSNR.
        acts: ``acts(module)`` -> whether any withheld frame is one the module is for; one without is kept unjudged.
    """
    best.restore(model)
    chosen = Selection(
        selected_step=best.step, final_step=final_step, selected_psnr=best.psnr, final_psnr=final_psnr, psnr=best.psnr
    )
    for module in MODULES:
        nets = module_heads(model, module)
        if not nets:
            chosen.kept[module] = False
            continue
        saved = [{k: v.clone() for k, v in net.state_dict().items()} for net in nets]
        chosen.judged[module] = acts(module)
        switch_off(nets)
        without = float(measure())
        chosen.psnr_without[module] = without
        chosen.kept[module] = without < chosen.psnr - margin_db or not chosen.judged[module]
        if chosen.kept[module]:
            for net, state in zip(nets, saved):
                net.load_state_dict(state)
        else:
            chosen.psnr = without
    return chosen
