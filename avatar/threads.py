"""Thread control for code made of many small tensor operations."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def single_threaded() -> Iterator[None]:
    """Run torch on one thread inside the block (restored afterwards).

    Many small tensor ops (the synthetic generator, the PBD solver) gain nothing from
    threads and slow down by an order of magnitude when cores are oversubscribed; one
    thread also makes results independent of the machine's core count.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
