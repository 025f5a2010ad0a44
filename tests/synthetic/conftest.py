"""Run the synthetic-data tests on one torch thread (many small tensor ops:
threads only add overhead, badly so on a busy machine)."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _single_thread(one_torch_thread: None) -> None:
    """Every test here runs on one torch thread (see tests/conftest.py)."""
