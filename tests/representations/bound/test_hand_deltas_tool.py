"""benchmarks/hand_deltas.py switches delta heads off for one render: inside, the switched head's delta is
exactly zero and the others act as before; after, the model is bit for bit the one it was."""

from __future__ import annotations

import torch

from avatar.representations.bound.gaussians import SH_C0
from benchmarks.hand_deltas import heads_off
from tests.representations.bound.conftest import NEAR, Scene


def test_heads_off_zeroes_one_head_and_restores_the_model(scene: Scene) -> None:
    model = scene.model()
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():  # a trained-looking H: every output layer non-zero
        for module in (model.hand_geo, model.hand_app):
            for head in module.heads.values():
                head.output.weight.normal_(0.0, 0.1, generator=gen)
                head.output.bias.normal_(0.0, 0.1, generator=gen)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    frame, vertices = scene.cond.frame(NEAR), scene.meshes.vertices[NEAR]
    hand = model.hand_index
    with torch.no_grad():
        before = model(frame, vertices)
        with heads_off(model, {"hand_app": ("c",)}):
            colour_off = model(frame, vertices)
        after = model(frame, vertices)
    base_rgb = (0.5 + SH_C0 * model.gaussians.sh_dc).clamp_min(0.0)  # SH degree 0, no delta
    assert torch.equal(colour_off.colors[hand], base_rgb[hand])
    assert not torch.equal(before.colors[hand], colour_off.colors[hand])
    assert torch.equal(colour_off.opacities, before.opacities) and torch.equal(colour_off.means, before.means)
    assert all(torch.equal(v, state[k]) for k, v in model.state_dict().items())
    assert torch.equal(after.colors, before.colors)
