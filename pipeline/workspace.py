"""Where a subject's artifacts live, and how a stage directory is published atomically.

Layout under ``paths.outputs``::

    <outputs>/<subject>/<stage>/            a completed stage (manifest last)
    <outputs>/<subject>/.tmp/<stage>-<id>/  a stage being written (never read)
    <outputs>/<subject>/.locks/<stage>.lock one lock per subject and stage: exclusive while the stage is
                                            decided and written, shared while a stage that reads it runs
    <outputs>/<subject>/.scratch/<stage>-<key>/  checkpoints of an unfinished stage, kept across
                                            killed runs with the same cache key, removed on success

A stage is written into ``.tmp`` and renamed into place. If a previous version
exists it is first renamed aside, so at every instant the final path holds
either the complete old artifact, nothing, or the complete new one: a process
killed at any point leaves nothing that a later run takes for whole.
"""

from __future__ import annotations

import os
import re
import shutil
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from pipeline.locks import LockTimeout, flock_all

__all__ = ["LockTimeout", "SUBJECT_RULE", "Workspace", "outputs_problem", "subject_problem"]

SUBJECT_RULE = "letters, digits, '-' or '_', starting with a letter or digit"
_SUBJECT = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")


def subject_problem(subject: object) -> str | None:
    """Why ``subject`` cannot name a subject folder, or ``None`` when it can."""
    if not isinstance(subject, str) or not _SUBJECT.fullmatch(subject):
        return f"subject={subject!r}: use {SUBJECT_RULE}, e.g. subject=synth_a"
    return None


def outputs_problem(outputs: str | Path) -> str | None:
    """Why ``paths.outputs`` cannot hold artifacts (a file, not writable), or ``None`` when it can."""
    path = Path(outputs).absolute()
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return (f"paths.outputs={outputs}: {existing} is a file, not a folder; point paths.outputs at a folder "
                f"(it is created if missing)")
    if not os.access(existing, os.W_OK | os.X_OK):
        return (f"paths.outputs={outputs}: {existing} is not writable (read-only file system or no permission); "
                f"choose a writable folder, e.g. paths.outputs=$HOME/interactavatar-outputs")
    return None


class Workspace:
    """The artifact tree of one subject."""

    def __init__(self, outputs: Path, subject: str) -> None:
        problem = subject_problem(subject)
        if problem:
            raise ValueError(problem)
        self.root = Path(outputs) / subject
        self.subject = subject

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    @property
    def _tmp_root(self) -> Path:
        return self.root / ".tmp"

    @contextmanager
    def lock(self, stage: str, reads: Sequence[str], order: Sequence[str], timeout_s: float) -> Iterator[None]:
        """Write lock on ``stage`` and read locks on the stages it ``reads``, across processes.

        While held, no other run can write ``stage`` or replace any of ``reads``; other
        readers of ``reads`` may run alongside. Locks are taken in ``order`` (the DAG's
        topological order), so runs never deadlock.
        """
        lock_dir = self.root / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        wanted = {name: True for name in reads} | {stage: False}
        requests = [(lock_dir / f"{name}.lock", wanted[name], f"stage '{name}' of subject '{self.subject}'")
                    for name in order if name in wanted]
        with flock_all(requests, timeout_s):
            yield

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
        """Remove every scratch dir of ``stage`` (after it was published or found cached; lock held)."""
        root = self.root / ".scratch"
        if root.is_dir():
            for p in root.glob(f"{stage}-*"):
                shutil.rmtree(p, ignore_errors=True)

    def discard_leftovers(self, stage: str) -> None:
        """Remove what killed or failed runs of ``stage`` left behind (temporary dirs, checkpoints).

        Call with the stage's write lock held and only when the stage is whole: no live
        run can be writing either, and no later run can resume from them.
        """
        self.discard_stale_tmp(stage)
        self.discard_scratch(stage)

    def discard_empty_scratch(self, scratch: Path) -> None:
        """Remove ``scratch`` if the stage left nothing in it to resume from (after a failure)."""
        try:
            scratch.rmdir()
        except OSError:
            pass  # not empty: a checkpoint the next run with the same key resumes from

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
