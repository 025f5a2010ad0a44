"""NeRF positional encoding gamma(x) (Mildenhall et al. 2020, Eq. 4)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def positional_encoding(x: Tensor, num_frequencies: int, include_input: bool = True) -> Tensor:
    """gamma(x) = (x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(L-1) pi x), cos(2^(L-1) pi x)), per coordinate.

    Args:
        x: (..., D) inputs, best of unit size (the caller normalises them).
        num_frequencies: L >= 0 octaves.
        include_input: prepend x itself (as NeRF's implementation does).
    Returns:
        (..., encoded_dim(D, L, include_input)), ordered [x, sin f0, cos f0, sin f1, cos f1, ...]
        with each block D wide.
    """
    if num_frequencies < 0:
        raise ValueError(f"num_frequencies must be >= 0, got {num_frequencies}")
    parts = [x] if include_input else []
    for k in range(num_frequencies):
        angle = (2.0**k * math.pi) * x
        parts += [torch.sin(angle), torch.cos(angle)]
    return torch.cat(parts, dim=-1) if parts else x[..., :0]


def encoded_dim(dim: int, num_frequencies: int, include_input: bool = True) -> int:
    """Width of :func:`positional_encoding` of a ``dim``-wide input."""
    return dim * (2 * num_frequencies + int(include_input))
