"""The delta MLPs and the stage-two step as made faster for issue 33 against the per-head reference they replace:
the same function and gradients to float32 rounding, the same initialisation bit for bit, the same interaction
distances to rounding, and the same short stage-two loss curve to rounding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor

from avatar.nets.mlp import DeltaHeads, DeltaMLP, SplitLinear, delta_heads
from avatar.representations.bound import dynamic_model
from avatar.representations.bound.dynamic_model import nearest_distance
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from tests.float_agreement import assert_within_ulps
from tests.representations.bound.conftest import Scene

# float32 rounding of a few layers of 16-128 units: relative to the largest entry of each compared tensor
RTOL = 1e-5


def _reference_split(layer: SplitLinear, point: Tensor, frame: Tensor) -> Tensor:
    """The split layer as it was: the point product, then the per-frame term added as a second (N, out) sum."""
    out = layer.point(point)
    return out + layer.frame(frame) if layer.frame is not None else out


def reference_forward(mlp: DeltaMLP, point: Tensor | tuple[Tensor, ...], frame: Tensor) -> Tensor:
    """One head as it was evaluated before issue 33: concatenated point inputs, the skip added after the middle
    layer's product, the LeakyReLU out of place."""
    point = torch.cat(point, dim=-1) if isinstance(point, tuple) else point
    h = mlp.act(mlp.norms[0](_reference_split(mlp.input_layer, point, frame)))
    for i, layer in enumerate(mlp.hidden, start=1):
        z = layer(h)
        if i == mlp.skip_at:
            z = z + _reference_split(mlp.skip, point, frame)
        h = mlp.act(mlp.norms[i](z))
    return mlp.output(h)


def _close(actual: Tensor, expected: Tensor) -> None:
    scale = float(expected.detach().abs().max().clamp_min(1e-30))
    torch.testing.assert_close(actual, expected, rtol=0.0, atol=RTOL * scale)


@pytest.mark.parametrize(("depth", "frame_dim", "parts"), [(1, 7, 1), (2, 0, 1), (4, 7, 2), (6, 9, 2)])
def test_delta_heads_equal_the_per_head_reference_values_and_gradients(depth: int, frame_dim: int, parts: int) -> None:
    torch.manual_seed(0)
    heads = DeltaHeads({"mu": 3, "s": 3, "o": 1}, point_dim=11, frame_dim=frame_dim, width=16, depth=depth)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for head in heads.heads.values():  # trained output layers, so that every layer matters
            head.output.weight.normal_(0.0, 0.3, generator=gen)
            head.output.bias.normal_(0.0, 0.3, generator=gen)
    code = torch.randn(23, 11 - 4 * (parts - 1), generator=gen)
    learned = torch.randn(23, 4, generator=gen, requires_grad=True)  # e.g. the point features of H_app
    frame = torch.randn(frame_dim, generator=gen, requires_grad=True)
    point = (code, learned) if parts == 2 else code
    weights = torch.randn(23, 3, generator=gen)

    def run(forward) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        heads.zero_grad(set_to_none=True)
        learned.grad = frame.grad = None
        out = forward()
        sum((v * weights[:, : v.shape[1]]).sum() for v in out.values()).backward()
        grads = {name: p.grad.clone() for name, p in heads.named_parameters()}
        grads |= {name: x.grad.clone() for name, x in (("point", learned), ("frame", frame)) if x.grad is not None}
        return out, grads

    out, grads = run(lambda: heads(point, frame))
    ref_out, ref_grads = run(lambda: {n: reference_forward(h, point, frame) for n, h in heads.heads.items()})
    for name in ref_out:
        _close(out[name], ref_out[name])
    assert grads.keys() == ref_grads.keys()
    for name in ref_grads:
        _close(grads[name], ref_grads[name])


def test_initialisation_and_state_dict_are_those_of_separate_heads() -> None:
    """A fresh module is the per-head MLPs drawn in order, bit for bit (networks.pt keeps its layout)."""
    torch.manual_seed(3)
    heads = DeltaHeads({"c": 3, "o": 1}, point_dim=9, frame_dim=5, width=8, depth=4)
    torch.manual_seed(3)
    separate = {"c": DeltaMLP(9, 5, 3, 8, 4), "o": DeltaMLP(9, 5, 1, 8, 4)}
    state = heads.state_dict()
    expected = {f"heads.{n}.{k}": v for n, mlp in separate.items() for k, v in mlp.state_dict().items()}
    assert state.keys() == expected.keys()
    assert all(torch.equal(state[k], expected[k]) for k in expected)
    assert all(not v.any() for k, v in state.items() if ".output." in k)


def reference_nearest_distance(points: Tensor, targets: Tensor, reach: float) -> Tensor:
    """The interaction distances as they were: ``torch.cdist`` and ``min`` over the box-filtered points."""
    out = torch.full((points.shape[0],), math.inf, dtype=points.dtype)
    if targets.shape[0] == 0 or points.shape[0] == 0:
        return out
    lo, hi = targets.min(0).values - reach, targets.max(0).values + reach
    near = ((points >= lo) & (points <= hi)).all(-1).nonzero()[:, 0]
    for start in range(0, near.shape[0], 4096):
        idx = near[start : start + 4096]
        out[idx] = torch.cdist(points[idx], targets).min(-1).values
    return out


def test_nearest_distance_is_cdists_to_rounding() -> None:
    """Two implementations of one formula (the chunks' matrix products are blocked differently from cdist's,
    and torch's kernels round differently per instruction set): within 16 ULPs of the largest distance, and
    the same points out of reach."""
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(5000, 3, generator=gen) * 0.3  # more than one chunk
    targets = torch.rand(300, 3, generator=gen) * 0.1 + 0.1
    ours, ref = nearest_distance(points, targets, 0.05), reference_nearest_distance(points, targets, 0.05)
    assert torch.equal(ours.isinf(), ref.isinf())
    assert_within_ulps(ours[ref.isfinite()], ref[ref.isfinite()], ulps=16, what="nearest distance")


def test_a_short_stage_two_gives_the_reference_loss_curve(scene: Scene, monkeypatch) -> None:
    """Eight steps (contact and not) with everything issue 33 changed against the same steps with the references
    (per-head MLP forward, unfused Adam, cdist distances): the same losses to rounding."""
    cfg = DynamicTrainConfig(steps=8, log_every=1, patch_weight=0.0, contact_fraction=0.5, max_contact_emphasis=1e9)
    contact = np.array([True, False])
    fast = train_dynamic(scene.model(), scene.views, scene.meshes, scene.cond, contact, cfg).log
    adam = torch.optim.Adam
    monkeypatch.setattr(torch.optim, "Adam", lambda *a, fused=None, **k: adam(*a, **k))
    monkeypatch.setattr(DeltaMLP, "forward", reference_forward)
    monkeypatch.setattr(dynamic_model, "nearest_distance", reference_nearest_distance)
    reference = train_dynamic(scene.model(), scene.views, scene.meshes, scene.cond, contact, cfg).log
    assert [r.step for r in fast] == [r.step for r in reference]
    assert sum(r.interaction_evaluations for r in reference) > 0  # I ran: its changes are covered
    assert [r.interaction_evaluations for r in fast] == [r.interaction_evaluations for r in reference]
    np.testing.assert_allclose([r.loss for r in fast], [r.loss for r in reference], rtol=1e-5)


@pytest.mark.parametrize(("depth", "frame_dim", "fixed_parts"), [(1, 7, 1), (2, 0, 2), (4, 7, 1), (6, 9, 2)])
@pytest.mark.parametrize("kind", ["per_parameter", "shared"])
def test_fixed_products_computed_once_give_the_same_deltas(depth: int, frame_dim: int, fixed_parts: int, kind: str):
    """The leading point blocks multiplied once (fixed_products), the rest and the frame at the call: the deltas of the
    whole call to rounding, also for a subset of the points (rows)."""
    torch.manual_seed(0)
    heads = delta_heads(kind, {"mu": 3, "s": 3, "o": 1}, point_dim=13, frame_dim=frame_dim, width=16, depth=depth)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for layer in heads.output_layers():
            layer.weight.normal_(0.0, 0.3, generator=gen)
            layer.bias.normal_(0.0, 0.3, generator=gen)
    blocks = (torch.randn(23, 6, generator=gen), torch.randn(23, 4, generator=gen), torch.randn(23, 3, generator=gen))
    frame = torch.randn(frame_dim, generator=gen)
    fixed, rest = blocks[:fixed_parts], blocks[fixed_parts:]
    rows = torch.tensor([0, 5, 7, 22])
    with torch.no_grad():
        products = heads.fixed_products(fixed)
        whole, ours = heads(blocks, frame), heads(rest, frame, products)
        some = heads(tuple(b[rows] for b in rest), frame, tuple(p.rows(rows) for p in products))
    for name in whole:
        _close(ours[name], whole[name])
        _close(some[name], whole[name][rows])
