"""One small synthetic capture per test session, and one torch thread per test."""

from __future__ import annotations

import pytest

from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate


@pytest.fixture(autouse=True)
def _single_thread(one_torch_thread: None) -> None:
    """Every test here runs on one torch thread (see tests/conftest.py)."""


@pytest.fixture(scope="session")
def capture() -> SyntheticCapture:
    return generate(SyntheticConfig(subject="synth_a", sequence="train", image_size=96, num_frames=6, supersample=1))
