"""Statistics over seeds: whether two methods' mean scores differ beyond their spread."""

from __future__ import annotations

import numpy as np
from scipy.stats import ttest_ind


def welch_p(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sided p-value of Welch's t-test (unequal variances) of the means of ``a`` (n,) and ``b`` (m,); NaN
    with fewer than two values on a side or no spread at all."""
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size < 2 or b.size < 2 or (np.ptp(a) == 0 and np.ptp(b) == 0):
        return float("nan")
    return float(ttest_ind(a, b, equal_var=False).pvalue)
