"""Stated tolerances for comparing the floats of two implementations.

Two implementations of the same formula (the compiled rasterizer and the torch backend, a chunked
kernel and its one-shot reference) agree only to rounding: torch's own kernels take other paths on
other instruction sets (AVX2, AVX-512, AMX), the compiler may contract ``a * b + c`` into one FMA in
one and not the other, and a reduction's order depends on its blocking. So values computed by two
implementations are compared in units in the last place (ULPs) of the larger magnitude involved, and
integers rounded from such values (a rasterizer's pixel radii, ``ceil`` of a float) may differ by one
where the float lies within rounding of an integer. Bit-equality stays the rule where both sides run
the same code (a resume, a thread count, the smoke digests).
"""

from __future__ import annotations

import torch


def ulps_apart(actual: torch.Tensor, expected: torch.Tensor) -> torch.Tensor:
    """Each entry's difference in ULPs of ``max(|actual|, |expected|, scale)``.

    ``scale`` is the largest magnitude in ``expected``, so entries near zero are measured against the
    tensor's own size (a relative ULP count is meaningless at zero). Both tensors must be floating point
    of one dtype and shape; the result is float64 with their shape.
    """
    if actual.dtype != expected.dtype or actual.shape != expected.shape:
        shapes = f"{actual.dtype}{tuple(actual.shape)} != {expected.dtype}{tuple(expected.shape)}"
        raise ValueError(f"compare like with like: {shapes}")
    eps = torch.finfo(expected.dtype).eps
    a, e = actual.double(), expected.double()
    scale = e.abs().max() if e.numel() else torch.zeros((), dtype=torch.float64)
    magnitude = torch.maximum(torch.maximum(a.abs(), e.abs()), scale.expand_as(e))
    return (a - e).abs() / (eps * magnitude).clamp_min(torch.finfo(torch.float64).tiny)


def assert_within_ulps(actual: torch.Tensor, expected: torch.Tensor, ulps: float, what: str = "value") -> None:
    """Every entry within ``ulps`` ULPs (see :func:`ulps_apart`); NaN never agrees."""
    assert not torch.isnan(actual).any() and not torch.isnan(expected).any(), f"{what}: NaN"
    apart = ulps_apart(actual, expected)
    worst = apart.max().item() if apart.numel() else 0.0
    assert worst <= ulps, f"{what}: {worst:.1f} ULPs apart (tolerance {ulps})"


def assert_rounded_alike(actual: torch.Tensor, expected: torch.Tensor, at_most: int, what: str = "value") -> None:
    """Integers rounded from floats by two implementations: equal, or one apart in at most ``at_most``
    entries (the floats that fell within rounding of an integer)."""
    assert actual.shape == expected.shape, f"{what}: shape {tuple(actual.shape)} != {tuple(expected.shape)}"
    if not actual.numel():
        return
    diff = (actual.long() - expected.long()).abs()
    assert diff.max().item() <= 1, f"{what}: entries differ by {diff.max().item()}"
    apart = int((diff > 0).sum().item())
    assert apart <= at_most, f"{what}: {apart} entries differ by one (tolerance {at_most})"
