"""Deterministic solid (3D) value noise for procedural skin textures.

The noise is a function of a 3D point (e.g. a vertex's or a sample's position
on the canonical template, metres), so the texture sticks to the surface while
it moves and needs no UV layout.
"""

from __future__ import annotations

import torch

_PRIMES = (73856093, 19349663, 83492791)
_MASK = (1 << 31) - 1


def _mix(h: torch.Tensor) -> torch.Tensor:
    """Integer avalanche (one multiply-xorshift round) of 31-bit hashes (int64;
    products stay below 2**62)."""
    h = ((h >> 15) ^ h) * 0x2C1B3C6D & _MASK
    return (h >> 13) ^ h


def value_noise(points: torch.Tensor, frequency: float, seed: int) -> torch.Tensor:
    """Smooth value noise in [-1, 1].

    Args:
        points: (N, 3) positions in metres.
        frequency: lattice cells per metre (feature size ~ 1 / frequency).
        seed: selects an independent noise field.

    Returns:
        (N,) float32 noise, C1-continuous in ``points``: pseudo-random values at
        the integer lattice, blended with a quintic fade over each cell.
    """
    p = points.to(torch.float64) * frequency
    cell = torch.floor(p)
    f = (p - cell).to(torch.float32)
    w = f * f * f * (f * (f * 6 - 15) + 10)  # quintic fade, (N, 3)
    base = cell.to(torch.int64)
    # Per-axis hash terms of the cell's two lattice planes: (N, 2) each.
    terms = [((base[:, k, None] + torch.tensor([0, 1])) * _PRIMES[k]) & _MASK for k in range(3)]
    h = terms[0][:, :, None, None] ^ terms[1][:, None, :, None] ^ terms[2][:, None, None, :]
    h = _mix(h ^ (seed * 2654435761 & _MASK))  # (N, 2, 2, 2)
    values = (h & 0xFFFFFF).to(torch.float32) / float(1 << 24)
    wx, wy, wz = (torch.stack([1 - w[:, k], w[:, k]], dim=1) for k in range(3))
    weights = wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]
    return (weights * values).sum(dim=(1, 2, 3)) * 2 - 1


def fbm(points: torch.Tensor, frequency: float, octaves: int, seed: int) -> torch.Tensor:
    """Fractal sum of ``octaves`` value-noise layers (each twice the frequency and
    half the amplitude of the previous), normalised to [-1, 1]. (N, 3) -> (N,)."""
    total = torch.zeros(points.shape[0], dtype=torch.float32)
    norm = 0.0
    for octave in range(octaves):
        amp = 0.5**octave
        total += amp * value_noise(points, frequency * 2**octave, seed + 101 * octave)
        norm += amp
    return total / norm
