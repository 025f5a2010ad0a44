"""L_s and L_mu against their closed forms, the empty view, and the GPU's masked mean against the CPU's gathered one."""

from __future__ import annotations

import pytest
import torch

from avatar.losses import masked_visible_mean, position_regulariser, scale_regulariser, visible_mean


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(200, 3, generator=g), 0.4 * torch.randn(200, 3, generator=g), torch.rand(200, generator=g) > 0.4


def test_the_regularisers_are_their_closed_forms_over_the_visible_gaussians() -> None:
    scales, means, visible = _scene()
    rows = visible.nonzero()[:, 0].tolist()
    expected_s = sum(sum(max(float(scales[i, k]) - 0.4, 0.0) ** 2 for k in range(3)) for i in rows) / len(rows)
    expected_mu = sum(max(float(means[i].norm()) - 0.2, 0.0) ** 2 for i in rows) / len(rows)
    assert float(scale_regulariser(scales, visible, 0.4)) == pytest.approx(expected_s, rel=1e-5)
    assert float(position_regulariser(means, visible, 0.2)) == pytest.approx(expected_mu, rel=1e-5)


def test_no_visible_gaussian_gives_zero_with_a_graph() -> None:
    scales = torch.full((5, 3), 2.0, requires_grad=True)
    none = torch.zeros(5, dtype=torch.bool)
    for loss in (scale_regulariser(scales, none, 0.4), masked_visible_mean(scales.sum(-1), none)):
        assert float(loss.detach()) == 0.0
        loss.backward()
        assert torch.equal(scales.grad, torch.zeros_like(scales))
        scales.grad = None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_gpus_masked_mean_is_the_cpus_gathered_mean(seed: int) -> None:
    """The same value to float32 rounding (the order of the sum differs), and the same gradients."""
    values, _, visible = _scene(seed)
    a, b = values[:, 0].clone().requires_grad_(True), values[:, 0].clone().requires_grad_(True)
    gathered, masked = visible_mean(a, visible), masked_visible_mean(b, visible)
    assert float(masked) == pytest.approx(float(gathered), rel=1e-6)
    gathered.backward()
    masked.backward()
    torch.testing.assert_close(b.grad, a.grad)
