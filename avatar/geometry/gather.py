"""Gathering rows by index with a backward pass that is the same bit for bit on any number of threads.

Advanced indexing (``values[index]``) differentiates into ``index_put_`` with accumulation, which on the CPU sums the
gradients of a row that several indices repeat (a vertex shared by its triangles, a point in several neighbourhoods)
with parallel atomic additions: in an order that depends on the threads' timing, so two runs of the same training
differ in their last bits, and then everywhere. ``index_select`` differentiates into ``index_add_``, which sums them
in the order of the indices.
"""

from __future__ import annotations

import torch


def gather_rows(values: torch.Tensor, index: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """``values`` indexed by ``index`` along ``dim``: ``values[index]`` for ``dim=0``, ``values[..., index, :]`` for
    ``dim=-2``, with a reproducible backward (see the module's docstring).

    Args:
        values: (..., N, ...) any tensor; ``dim`` is the axis of the N rows.
        index: (*I) int64 row indices in [0, N).
    Returns:
        ``values`` with its axis ``dim`` replaced by ``index``'s shape (*I).
    """
    dim = dim % values.dim()
    flat = torch.index_select(values, dim, index.reshape(-1))
    return flat.reshape(*values.shape[:dim], *index.shape, *values.shape[dim + 1 :])
