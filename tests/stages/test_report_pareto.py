"""The report's Pareto front against brute force."""

from __future__ import annotations

import numpy as np

from reporting.comparison import pareto_front


def _brute(cost: np.ndarray, quality: np.ndarray) -> np.ndarray:
    keep = []
    for i in range(len(cost)):
        beaten = any(
            cost[j] <= cost[i] and quality[j] >= quality[i] and (cost[j] < cost[i] or quality[j] > quality[i])
            for j in range(len(cost))
        )
        keep.append(not beaten)
    return np.array(keep)


def test_pareto_front_matches_brute_force_with_ties():
    rng = np.random.default_rng(0)
    for _ in range(50):
        cost, quality = rng.integers(0, 5, 12).astype(float), rng.integers(0, 5, 12).astype(float)
        np.testing.assert_array_equal(pareto_front(cost, quality), _brute(cost, quality))


def test_the_cheapest_and_the_best_are_on_the_front():
    front = pareto_front(np.array([10.0, 20.0, 30.0, 25.0]), np.array([28.0, 29.5, 30.0, 29.0]))
    np.testing.assert_array_equal(front, [True, True, True, False])
