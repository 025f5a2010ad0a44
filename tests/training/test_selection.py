"""The selection rule of stage two (avatar.training.selection) on a stand-in model whose validation score is a
known function of which modules are on: the best step, ties, and the margin."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from avatar.nets.mlp import DeltaHeads
from avatar.training.selection import BestStep, SelectionConfig, module_heads, select, switch_off


class _Model(nn.Module):
    """hand_geo, hand_app and interaction heads with non-zero output layers (a trained model), and a value."""

    def __init__(self, interaction: bool = True) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.hand_geo = DeltaHeads({"mu": 3}, 4, 2, 8, 2)
        self.hand_app = DeltaHeads({"c": 3}, 4, 2, 8, 2)
        self.interaction = DeltaHeads({"mu": 3, "o": 1}, 4, 2, 8, 2) if interaction else None
        self.value = nn.Parameter(torch.zeros(()))
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(torch.randn(p.shape, generator=gen))


def _on(model: _Model, module: str) -> bool:
    return any(bool(h.output.weight.abs().sum() > 0) for net in module_heads(model, module) for h in net.heads.values())


def _psnr(model: _Model, hand_worth: float, interaction_worth: float) -> float:
    """30 dB plus what each module is worth while it is on."""
    return 30.0 + hand_worth * _on(model, "hand_mlp") + interaction_worth * _on(model, "interaction")


def test_the_best_step_wins_and_ties_keep_the_earlier_one():
    model, best = _Model(), BestStep()
    states = {}
    for step, psnr in ((0, 30.0), (50, 31.0), (100, 31.0), (150, 30.5)):
        with torch.no_grad():
            model.value.fill_(step)
        states[step] = {k: v.clone() for k, v in model.state_dict().items()}
        best.offer(step, psnr, model)
    assert (best.step, best.psnr, best.offered) == (50, 31.0, 150)
    best.restore(model)
    assert float(model.value.detach()) == 50.0
    resumed = BestStep()
    resumed.load_state(best.state())  # a checkpoint keeps the choice
    model.value.data.fill_(0)
    resumed.restore(model)
    assert float(model.value.detach()) == 50.0 and (resumed.step, resumed.psnr) == (50, 31.0)


@pytest.mark.parametrize(
    ("hand_worth", "interaction_worth", "kept_hand", "kept_interaction"),
    [
        (0.5, 0.3, True, True),  # both pay for themselves
        (0.5, 0.01, True, False),  # I is worth less than the margin: off
        (-0.2, 0.3, False, True),  # H lowers validation PSNR: off
        (0.05, 0.06, False, True),  # exactly the margin is not enough
    ],
)
def test_a_module_stays_only_when_it_is_worth_more_than_the_margin(
    hand_worth, interaction_worth, kept_hand, kept_interaction
):
    model, best = _Model(), BestStep()
    best.offer(7, _psnr(model, hand_worth, interaction_worth), model)
    hand_before = {k: v.clone() for k, v in model.hand_app.state_dict().items()}
    chosen = select(model, best, 9, 29.0, lambda: _psnr(model, hand_worth, interaction_worth), margin_db=0.05)
    assert chosen.kept == {"hand_mlp": kept_hand, "interaction": kept_interaction}
    assert (chosen.selected_step, chosen.final_step, chosen.final_psnr) == (7, 9, 29.0)
    assert _on(model, "hand_mlp") == kept_hand and _on(model, "interaction") == kept_interaction
    assert chosen.psnr == pytest.approx(_psnr(model, hand_worth, interaction_worth))
    if kept_hand:  # a kept module comes back bit for bit
        assert all(torch.equal(v, hand_before[k]) for k, v in model.hand_app.state_dict().items())
    assert chosen.psnr_without["hand_mlp"] == pytest.approx(30.0 + interaction_worth)
    metrics = chosen.metrics()
    assert metrics["kept_hand_mlp"] is kept_hand and metrics["selected_step"] == 7


def test_a_module_the_method_never_built_is_not_kept_and_not_measured():
    model, best = _Model(interaction=False), BestStep()
    best.offer(0, 30.5, model)
    chosen = select(model, best, 0, 30.5, lambda: _psnr(model, 0.5, 0.0), margin_db=0.05)
    assert chosen.kept == {"hand_mlp": True, "interaction": False}
    assert "interaction" not in chosen.psnr_without


def test_a_module_with_no_withheld_frame_it_is_for_is_kept_unjudged():
    """I when no withheld frame has contact: switching it off changes next to nothing there, which is no evidence
    that it is worth nothing (issue 53's (c): I was switched off in every seed that way)."""
    model, best = _Model(), BestStep()
    best.offer(5, _psnr(model, 0.5, 0.0), model)
    chosen = select(
        model, best, 5, 30.5, lambda: _psnr(model, 0.5, 0.0), margin_db=0.05, acts=lambda m: m != "interaction"
    )
    assert chosen.kept == {"hand_mlp": True, "interaction": True}
    assert chosen.judged == {"hand_mlp": True, "interaction": False}
    assert _on(model, "interaction")  # restored, bit for bit, not left switched off
    metrics = chosen.metrics()
    assert metrics["selection_judged_interaction"] is False and metrics["kept_interaction"] is True
    judged = select(_Model(), _best(), 5, 30.5, lambda: 30.5, margin_db=0.05)  # acting and worth nothing: off
    assert judged.kept["interaction"] is False and judged.judged["interaction"] is True


def _best() -> BestStep:
    best = BestStep()
    best.offer(5, 30.5, _Model())
    return best


def test_switched_off_heads_output_exactly_zero():
    net = _Model().hand_geo
    switch_off([net])
    out = net(torch.randn(5, 4), torch.randn(2))
    assert all(torch.equal(v, torch.zeros_like(v)) for v in out.values())


def test_a_negative_margin_is_refused():
    assert SelectionConfig(True, -0.1).problems() == ["margin_db=-0.1: must be >= 0 (dB)"]
    assert SelectionConfig(True, 0.0).problems() == []
