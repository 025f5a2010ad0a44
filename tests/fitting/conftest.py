"""One small synthetic capture per test session, and one torch thread per test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def capture() -> SyntheticCapture:
    return generate(SyntheticConfig(subject="synth_a", sequence="train", image_size=96, num_frames=6,
                                    supersample=1))
