"""Shared/exclusive file locks between processes (``flock``), with a timeout.

A stage being written holds its own lock exclusively; a stage that reads it holds
it shared for as long as it runs, so an upstream artifact can never be replaced
under a reader. The kernel releases ``flock`` locks when their process dies, so a
``kill -9`` never leaves a lock behind.

Fairness: a run passes the lock's turnstile (``<lock>.queue``, held exclusively
while it waits for the lock) on its way in and leaves it once it holds the lock.
A later reader therefore cannot pass a writer that waits, as it could with
bare ``flock``: a run reading a shared stage stage after stage (a method's chain
from warm-up to report) used to keep a run that must rewrite that stage waiting
for its whole chain, because a 50 ms poll missed every gap between two stages.
Now the writer gets the lock when the stage that holds it ends, and the reader's
next stage waits for the writer.

Deadlock freedom: a run takes every lock it needs for one stage at once, in the
DAG's topological order, and releases them all when the stage ends. Two runs
wanting overlapping sets therefore acquire them in the same order; a turnstile
ranks just before its lock, so the order stays total.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import NoReturn

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
    deadline = time.monotonic() + timeout_s
    with ExitStack() as held:
        # Every run passes the turnstile on its way to the lock, and one that waits for the lock waits inside it,
        # so no later run can take the lock first.
        with _locked(path.with_name(path.name + ".queue"), fcntl.LOCK_EX, deadline, path, what):
            held.enter_context(_locked(path, fcntl.LOCK_SH if shared else fcntl.LOCK_EX, deadline, path, what))
        yield


@contextmanager
def _locked(file: Path, mode: int, deadline: float, path: Path, what: str) -> Iterator[None]:
    """Hold ``mode`` on ``file`` (created if missing) once it is free, or :class:`LockTimeout` at ``deadline``
    naming lock ``path``."""
    fd = os.open(file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        _wait(fd, mode, deadline, path, what)
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _try(fd: int, mode: int) -> bool:
    """Take ``mode`` on ``fd`` if that is possible now."""
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _wait(fd: int, mode: int, deadline: float, path: Path, what: str) -> None:
    """Poll for ``mode`` on ``fd`` until it is taken, or :class:`LockTimeout` at ``deadline``."""
    while not _try(fd, mode):
        if time.monotonic() >= deadline:
            _timeout(path, what)
        time.sleep(_POLL_S)


def _timeout(path: Path, what: str) -> NoReturn:
    raise LockTimeout(f"{what} is locked by another run ({path}); wait for it or raise run.lock_timeout_s")


@contextmanager
def flock_all(requests: Sequence[tuple[Path, bool, str]], timeout_s: float) -> Iterator[None]:
    """Hold every ``(path, shared, what)`` lock, taken in the given order (callers sort it topologically)."""
    deadline = time.monotonic() + timeout_s
    with ExitStack() as stack:
        for path, shared, what in requests:
            stack.enter_context(flock(path, shared=shared, timeout_s=max(deadline - time.monotonic(), 0.0), what=what))
        yield
