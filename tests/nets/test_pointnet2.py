"""PointNet++ encoder: FPS and ball query against brute-force loops, one set abstraction against a slow
per-centre reference, and the encoder's order invariance, degenerate inputs and gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.nets.pointnet2 import (
    PointNet2Encoder,
    SetAbstraction,
    ball_query,
    canonical_order,
    classic_widths,
    farthest_point_sample,
    farthest_point_sample_on_device,
    fps_start,
    fps_start_index,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: A narrow encoder for the tests that do not need the classic widths.
SMALL = dict(
    feature_dim=32, centres=(64, 16), radii=(0.2, 0.4), neighbours=(16, 32), widths=((16, 16), (16, 32), (32, 32))
)


def fps_reference(points: np.ndarray, num_samples: int, start: int) -> list[int]:
    """Brute-force FPS: repeatedly the point maximising its min squared distance to the chosen set."""
    n = len(points)
    chosen = [start] if n else []
    while len(chosen) < min(num_samples, n):
        best, best_d = -1, -1.0
        for i in range(n):
            d = min(float(((points[i] - points[j]) ** 2).sum()) for j in chosen)
            if d > best_d:
                best, best_d = i, d
        chosen.append(best)
    return chosen


def ball_query_reference(points: np.ndarray, centres: np.ndarray, radius: float, k: int) -> list[list[int]]:
    """Brute force: the first k indices within radius (inclusive), padded with the first found, or the
    nearest point everywhere when none is found."""
    rows = []
    for c in centres:
        d2 = [float(((p - c) ** 2).sum()) for p in points]
        found = [i for i in range(len(points)) if d2[i] <= radius * radius][:k]
        if not found:
            found = [int(np.argmin(d2))]
        rows.append(found + [found[0]] * (k - len(found)))
    return rows


# --- farthest point sampling ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed, n, m, start", [(0, 40, 12, 0), (1, 57, 20, 13), (2, 8, 8, 7), (3, 25, 1, 4)])
def test_fps_matches_brute_force(seed: int, n: int, m: int, start: int) -> None:
    points = np.random.default_rng(seed).normal(size=(n, 3))  # float64: no ties
    got = farthest_point_sample(torch.from_numpy(points), m, start=start)
    assert got.dtype == torch.int64
    assert got.tolist() == fps_reference(points, m, start)


@pytest.mark.parametrize("n, m", [(50, 50), (50, 17), (10, 30)])
def test_fps_count_and_no_duplicates(n: int, m: int) -> None:
    points = torch.rand(n, 3, generator=torch.Generator().manual_seed(n + m))
    got = farthest_point_sample(points, m)
    assert len(got) == min(n, m)
    assert len(set(got.tolist())) == len(got)


def test_fps_repeated_points_stay_distinct() -> None:
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0]]).repeat(5, 1)  # every point twice or more
    got = farthest_point_sample(points, 10)
    assert sorted(got.tolist()) == list(range(10))


def test_fps_empty_and_single() -> None:
    empty = farthest_point_sample(torch.empty(0, 3), 5)
    assert empty.shape == (0,) and empty.dtype == torch.int64
    assert farthest_point_sample(torch.zeros(1, 3), 5).tolist() == [0]


@pytest.mark.parametrize(
    "points, m",
    [
        (torch.rand(300, 3, generator=torch.Generator().manual_seed(6)), 64),  # float32: ties possible
        (torch.rand(50, 3, generator=torch.Generator().manual_seed(7)), 50),  # every point
        (torch.tensor([[0.0, 0, 0], [1, 0, 0]]).repeat(5, 1), 10),  # only repeats left after two
        (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]).repeat(4, 1), 7),
        (torch.zeros(1, 3), 5),
        (torch.rand(0, 3), 5),
    ],
)
def test_fps_without_host_reads_picks_the_same_indices(points: torch.Tensor, m: int) -> None:
    """The GPU's FPS (no value read on the host) against the host version, bit for bit, ties and repeats too."""
    start = fps_start(points) if len(points) else 0
    expected = farthest_point_sample(points, m, start=start)
    got = farthest_point_sample_on_device(points, m, fps_start_index(points) if len(points) else torch.tensor(0))
    assert got.dtype == torch.int64 and got.tolist() == expected.tolist()


def test_fps_start_and_canonical_order_ignore_input_order() -> None:
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(4))
    perm = torch.randperm(300, generator=torch.Generator().manual_seed(5))
    assert torch.equal(points[perm][fps_start(points[perm])], points[fps_start(points)])
    assert torch.equal(points[perm][canonical_order(points[perm])], points[canonical_order(points)])


# --- ball query ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("chunk_elements", [None, 7, 1])
def test_ball_query_matches_brute_force(chunk_elements: int | None) -> None:
    rng = np.random.default_rng(6)
    points = rng.uniform(size=(80, 3))
    centres = np.concatenate([points[:10], rng.uniform(size=(5, 3))])
    got = ball_query(torch.from_numpy(points), torch.from_numpy(centres), 0.3, 6, chunk_elements=chunk_elements)
    assert got.dtype == torch.int64 and got.shape == (15, 6)
    assert got.tolist() == ball_query_reference(points, centres, 0.3, 6)


def test_ball_query_boundary_no_neighbour_and_padding() -> None:
    points = torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [0.25, 0, 0], [3.0, 0, 0], [0, 0.75, 0]])
    centres = torch.tensor([[0.0, 0, 0], [10.0, 0, 0], [0.0, 0.5, 0]])
    got = ball_query(points, centres, 0.5, 4, chunk_elements=5)  # one centre per chunk
    assert got[0].tolist() == [0, 1, 2, 0]  # (0.5, 0, 0) at exactly the radius is inside; padded with 0
    assert got[1].tolist() == [3, 3, 3, 3]  # nothing within the radius: the nearest point
    assert got[2].tolist() == [0, 4, 0, 0]  # both at exactly 0.5
    assert got.tolist() == ball_query_reference(points.numpy(), centres.numpy(), 0.5, 4)


def test_ball_query_more_slots_than_points() -> None:
    got = ball_query(torch.zeros(2, 3), torch.zeros(1, 3), 0.1, 5)
    assert got.tolist() == [[0, 1, 0, 0, 0]]


# --- set abstraction -----------------------------------------------------------------------------------------


def test_set_abstraction_matches_slow_reference() -> None:
    torch.manual_seed(7)
    xyz = torch.rand(120, 3, dtype=torch.float64)
    features = torch.randn(120, 5, dtype=torch.float64)
    layer = SetAbstraction(20, 0.3, 8, 5, (12, 16)).double()
    new_xyz, new_features = layer(xyz, features)

    centres = xyz[farthest_point_sample(xyz, 20, start=fps_start(xyz))]
    neighbours = ball_query_reference(xyz.numpy(), centres.numpy(), 0.3, 8)
    expected = []
    for centre, rows in zip(centres, neighbours):
        x = torch.cat([(xyz[rows] - centre) / 0.3, features[rows]], dim=1)
        for module in layer.mlp:
            x = module(x)
        expected.append(x.max(dim=0).values)
    assert torch.equal(new_xyz, centres)
    torch.testing.assert_close(new_features, torch.stack(expected), atol=1e-6, rtol=0)


def test_set_abstraction_without_features_and_few_points() -> None:
    layer = SetAbstraction(16, 0.2, 4, 0, (8,))
    new_xyz, new_features = layer(torch.rand(5, 3))
    assert new_xyz.shape == (5, 3) and new_features.shape == (5, 8)


# --- encoder -------------------------------------------------------------------------------------------------


def test_encoder_ignores_point_order() -> None:
    torch.manual_seed(8)
    encoder = PointNet2Encoder(**SMALL)
    points = torch.rand(600, 3) * 0.6  # dense: the balls hold more points than they keep
    assert (torch.cdist(points, points) <= 0.2).sum(dim=1).min() > 16
    perm = torch.randperm(600)
    torch.testing.assert_close(encoder(points[perm]), encoder(points), atol=1e-5, rtol=0)


def test_encoder_ignores_point_order_with_ties() -> None:
    torch.manual_seed(11)
    encoder = PointNet2Encoder(**SMALL)
    axis = torch.arange(8) / 8.0
    grid = torch.cartesian_prod(axis, axis, axis)  # tied FPS distances everywhere; every point twice
    points = torch.cat([grid, grid])
    perm = torch.randperm(len(points))
    assert torch.equal(encoder(points[perm]), encoder(points))


def test_encoder_empty_input() -> None:
    encoder = PointNet2Encoder(**SMALL)
    out = encoder(torch.empty(0, 3))
    assert out.shape == (32,) and torch.isfinite(out).all()
    out.sum().backward()
    assert encoder.empty.grad is not None and encoder.empty.grad.abs().sum() > 0


@pytest.mark.parametrize(
    "points, scale",
    [
        (torch.tensor([[0.1, -0.2, 0.3]]), 1.0),
        (torch.full((50, 3), 0.25), 1.0),
        (torch.rand(200, 3, generator=torch.Generator().manual_seed(9)) * 1e6, 1e6),
        (torch.rand(200, 3, generator=torch.Generator().manual_seed(9)) * 1e-6, 1e-6),
    ],
)
def test_encoder_degenerate_inputs_stay_finite(points: torch.Tensor, scale: float) -> None:
    encoder = PointNet2Encoder(**{**SMALL, "scale": scale})
    out = encoder(points)
    assert out.shape == (32,) and torch.isfinite(out).all()
    out.square().sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in encoder.parameters() if p.grad is not None)


def test_every_parameter_gets_a_gradient() -> None:
    torch.manual_seed(10)
    encoder = PointNet2Encoder()  # classic widths, feature_dim 1024
    out = encoder(torch.rand(300, 3))
    assert out.shape == (1024,)
    (out * torch.randn(1024)).sum().backward()
    dead = [name for name, p in encoder.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not dead


def test_widths() -> None:
    assert classic_widths() == ((64, 64, 128), (128, 128, 256), (256, 512, 1024))
    assert classic_widths(256, 0.25) == ((16, 16, 32), (32, 32, 64), (64, 128, 256))
    reduced = PointNet2Encoder(feature_dim=256, width_multiplier=0.5)
    assert reduced.glob.mlp[0].in_features == 3 + 128
    with pytest.raises(ValueError):
        PointNet2Encoder(feature_dim=64, widths=((8,), (8,), (32,)))


def test_fps_ties_go_to_the_first_index() -> None:
    grid = np.array([[x, y, 0.0] for x in range(3) for y in range(3)])  # exact, tied squared distances
    for start in (0, 4, 8):
        assert farthest_point_sample(torch.from_numpy(grid), 9, start=start).tolist() == fps_reference(grid, 9, start)
