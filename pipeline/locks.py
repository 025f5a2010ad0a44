"""Shared/exclusive file locks between processes (``flock``), with a timeout.

A stage being written holds its own lock exclusively; a stage that reads it holds
it shared for as long as it runs, so an upstream artifact can never be replaced
under a reader. The kernel releases ``flock`` locks when their process dies, so a
``kill -9`` never leaves a lock behind.

Deadlock freedom: a run takes every lock it needs for one stage at once, in the
DAG's topological order, and releases them all when the stage ends. Two runs
wanting overlapping sets therefore acquire them in the same order.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path

_POLL_S = 0.05


class LockTimeout(RuntimeError):
    """Another run holds a lock for longer than we are willing to wait."""


@contextmanager
def flock(path: Path, *, shared: bool, timeout_s: float, what: str) -> Iterator[None]:
    """Hold ``path`` locked (shared or exclusive) for the ``with`` block.

    Args:
        path: the lock file (created if missing; never removed, so every process locks the same inode).
        shared: ``True`` for a reader's lock (many at once), ``False`` for the writer's (alone).
        timeout_s: give up after this long with :class:`LockTimeout`.
        what: words for the error message, e.g. ``"stage 'fit' of subject 'synth_a'"``.
    """
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        mode = (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, mode)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise LockTimeout(f"{what} is locked by another run ({path}); wait for it or raise "
                                      f"run.lock_timeout_s") from None
                time.sleep(_POLL_S)
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


@contextmanager
def flock_all(requests: Sequence[tuple[Path, bool, str]], timeout_s: float) -> Iterator[None]:
    """Hold every ``(path, shared, what)`` lock, taken in the given order (callers sort it topologically)."""
    deadline = time.monotonic() + timeout_s
    with ExitStack() as stack:
        for path, shared, what in requests:
            stack.enter_context(flock(path, shared=shared, timeout_s=max(deadline - time.monotonic(), 0.0),
                                      what=what))
        yield
