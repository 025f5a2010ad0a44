"""The cross-implementation tolerances of tests/float_agreement.py measure what they say."""

from __future__ import annotations

import pytest
import torch

from tests.float_agreement import assert_rounded_alike, assert_within_ulps, ulps_apart


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_step_of_nextafter_is_one_ulp_at_the_largest_magnitude(dtype: torch.dtype) -> None:
    x = torch.tensor([1.0, -1.0, 0.5], dtype=dtype)
    up = torch.nextafter(x, torch.full_like(x, 2.0))
    apart = ulps_apart(up, x)
    assert apart[0].item() == pytest.approx(1.0) and apart[1].item() == pytest.approx(0.5)
    assert apart[2].item() == pytest.approx(0.5)  # half the ULP of 1.0, the tensor's scale
    assert_within_ulps(up, x, ulps=1)
    with pytest.raises(AssertionError, match="ULPs apart"):
        assert_within_ulps(x * (1 + 8 * torch.finfo(dtype).eps), x, ulps=4)


def test_nan_and_mismatched_tensors_never_agree() -> None:
    x = torch.tensor([1.0, float("nan")])
    with pytest.raises(AssertionError, match="NaN"):
        assert_within_ulps(x, x, ulps=1e9)
    with pytest.raises(ValueError, match="like with like"):
        ulps_apart(torch.zeros(2), torch.zeros(2, dtype=torch.float64))


def test_rounded_integers_may_differ_by_one_in_few_entries() -> None:
    ref = torch.tensor([3, 4, 5, 6], dtype=torch.int32)
    assert_rounded_alike(ref + torch.tensor([0, 1, 0, 0], dtype=torch.int32), ref, at_most=1)
    with pytest.raises(AssertionError, match="2 entries"):
        assert_rounded_alike(ref + torch.tensor([1, 1, 0, 0], dtype=torch.int32), ref, at_most=1)
    with pytest.raises(AssertionError, match="differ by 2"):
        assert_rounded_alike(ref + torch.tensor([2, 0, 0, 0], dtype=torch.int32), ref, at_most=3)
