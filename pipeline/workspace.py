"""Where a subject's artifacts live, and how a stage directory is published atomically.

Layout under ``paths.outputs``::

    <outputs>/<subject>/<stage>/            a completed stage (manifest last)
    <outputs>/<subject>/.tmp/<stage>-<id>/  a stage being written (never read)
    <outputs>/<subject>/.locks/<stage>.lock one lock per subject and stage
    <outputs>/<subject>/.scratch/<stage>-<key>/  checkpoints of an unfinished stage, kept across
                                            killed runs with the same cache key, removed on success

A stage is written into ``.tmp`` and renamed into place. If a previous version
exists it is first renamed aside, so at every instant the final path holds
either the complete old artifact, nothing, or the complete new one: a process
killed at any point leaves nothing that a later run takes for whole.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from filelock import FileLock, Timeout


class LockTimeout(RuntimeError):
    """Another run holds a stage lock for longer than we are willing to wait."""


class Workspace:
    """The artifact tree of one subject."""

    def __init__(self, outputs: Path, subject: str) -> None:
        if not subject or "/" in subject or subject.startswith((".", "_")):
            raise ValueError(f"invalid subject name {subject!r}: use letters, digits, '-' or '_' (not leading)")
        self.root = Path(outputs) / subject
        self.subject = subject

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    @property
    def _tmp_root(self) -> Path:
        return self.root / ".tmp"

    @contextmanager
    def lock(self, stage: str, timeout_s: float) -> Iterator[None]:
        """Exclusive lock on one stage of this subject, across processes."""
        lock_dir = self.root / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        lock = FileLock(str(lock_dir / f"{stage}.lock"))
        try:
            lock.acquire(timeout=timeout_s)
        except Timeout as exc:
            raise LockTimeout(
                f"stage '{stage}' of subject '{self.subject}' is locked by another run "
                f"({lock_dir / f'{stage}.lock'}); wait for it or raise run.lock_timeout_s"
            ) from exc
        try:
            yield
        finally:
            lock.release()

    def new_tmp_dir(self, stage: str) -> Path:
        """A fresh, empty directory for writing ``stage``; call with the stage lock held."""
        self.discard_stale_tmp(stage)
        path = self._tmp_root / f"{stage}-{uuid.uuid4().hex[:12]}"
        path.mkdir(parents=True)
        return path

    def discard_stale_tmp(self, stage: str) -> None:
        """Remove leftovers of killed runs of ``stage`` (safe: the caller holds its lock)."""
        if self._tmp_root.is_dir():
            for p in self._tmp_root.glob(f"{stage}-*"):
                shutil.rmtree(p, ignore_errors=True)

    def scratch_dir(self, stage: str, key: str) -> Path:
        """Persistent scratch space (checkpoints) of ``stage`` for one cache ``key``.

        It survives a killed run so the next run with the same key can resume; a
        different key (config or inputs changed) never sees it.
        """
        path = self.root / ".scratch" / f"{stage}-{key[:16]}"
        path.mkdir(parents=True, exist_ok=True)
        return path

    def discard_scratch(self, stage: str) -> None:
        """Remove every scratch dir of ``stage`` (after it was published)."""
        root = self.root / ".scratch"
        if root.is_dir():
            for p in root.glob(f"{stage}-*"):
                shutil.rmtree(p, ignore_errors=True)

    def publish(self, stage: str, tmp_dir: Path) -> Path:
        """Move a completed ``tmp_dir`` to the stage's final path, replacing any old version."""
        final = self.stage_dir(stage)
        aside = None
        if final.exists():
            aside = self._tmp_root / f"{stage}-old-{uuid.uuid4().hex[:12]}"
            os.replace(final, aside)
        os.replace(tmp_dir, final)
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)
        return final
