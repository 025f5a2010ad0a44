"""Fixtures of the rasterizer tests: which kernels ``backend="gsplat"`` runs."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from avatar.render.gaussians import render as render_module
from avatar.render.gaussians.backend_gsplat import gsplat_available


@pytest.fixture
def gsplat_reference(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """``backend="gsplat"`` runs gsplat's PyTorch reference on the CPU tensors it is given
    (``gsplat_reference.gsplat_on_cpu``), also where a GPU is present; skipped where gsplat is not installed
    (``make test`` installs it with the test extra, without building its CUDA code)."""
    pytest.importorskip("gsplat", reason="gsplat is installed with the test extra (make test)")
    from gsplat_reference import gsplat_on_cpu

    monkeypatch.setattr(render_module, "gsplat_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # the adapter keeps CPU tensors on the CPU
    with gsplat_on_cpu():
        yield


@pytest.fixture
def gsplat_cuda() -> None:
    """``backend="gsplat"`` runs gsplat's CUDA kernels (CPU tensors are copied to the GPU and back);
    skipped without CUDA and gsplat (``make test-gpu`` runs these)."""
    if not gsplat_available():
        pytest.skip("needs CUDA and gsplat (pip install -e '.[cuda]'; make test-gpu)")


GSPLAT_KERNELS = ["reference", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.fixture(params=GSPLAT_KERNELS)
def gsplat_kernels(request: pytest.FixtureRequest) -> str:
    """Each of gsplat's kernels in turn: its PyTorch reference on the CPU, then (with a GPU) CUDA."""
    request.getfixturevalue(f"gsplat_{request.param}")
    return request.param
