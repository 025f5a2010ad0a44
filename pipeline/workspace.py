"""Where a subject's artifacts live, and how a stage directory is published atomically.

Layout under ``paths.outputs``::

    <outputs>/<subject>/<stage>/            a completed stage shared by every method (manifest last)
    <outputs>/<subject>/methods/<method>/<stage>/  a completed stage that depends on the method
                                            (``Stage.per_method``): one per method, side by side
    <outputs>/<subject>/.tmp/<artifact>-<id>/  an artifact being written (never read)
    <outputs>/<subject>/.locks/<artifact>.lock one lock per artifact: exclusive while it is written,
                                            shared while it is decided or a stage that reads it runs
    <outputs>/<subject>/.locks/<artifact>.lock.queue  its turnstile: a run waiting for the lock waits in
                                            it, so later runs queue behind (pipeline.locks)
    <outputs>/<subject>/.locks/<stage>#<key>.lock  held by the run computing a per-method artifact with
                                            that cache key: a method with the same key waits, then shares it
    <outputs>/<subject>/.scratch/<artifact>-<key>/  checkpoints of an unfinished stage, kept across
                                            killed runs with the same cache key, removed on success

``<artifact>`` is the artifact's id: the stage name for a shared stage, ``<stage>@<method>`` for a
per-method one (:class:`Artifact`).

A stage is written into ``.tmp`` and renamed into place. If a previous version
exists it is first renamed aside, so at every instant the final path holds
either the complete old artifact, nothing, or the complete new one: a process
killed at any point leaves nothing that a later run takes for whole.
"""

from __future__ import annotations

import errno
import glob
import json
import os
import re
import shutil
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

from data_schemas.names import FOLDER_NAME_RULE, folder_name_problem
from pipeline.locks import LockTimeout, flock, flock_all

__all__ = [
    "Artifact",
    "LockTimeout",
    "METHODS_DIR",
    "SUBJECT_RULE",
    "Workspace",
    "method_problem",
    "method_run",
    "outputs_problem",
    "run_overrides",
    "seed_problem",
    "subject_problem",
]

SUBJECT_RULE = FOLDER_NAME_RULE
METHODS_DIR = "methods"
_UNIQUE_HEX = 12  # hex digits naming one temporary dir of an artifact
_SCRATCH_KEY_HEX = 16  # hex digits of the cache key naming one scratch dir of an artifact
ATTEMPT_FILE = "_attempt.json"  # in a scratch dir: when the run now using it started, and what it carries


def subject_problem(subject: object) -> str | None:
    """Why ``subject`` cannot name a subject folder, or ``None`` when it can."""
    problem = folder_name_problem(subject)
    return None if problem is None else f"subject={subject!r}: {problem}, e.g. subject=synth_a"


def method_problem(method: object, key: str = "method.name") -> str | None:
    """Why ``method`` cannot name a method folder, or ``None`` when it can."""
    problem = folder_name_problem(method)
    return None if problem is None else f"{key}={method!r}: {problem}, e.g. method=interactavatar"


def method_run(method: str, seed: int = 0) -> str:
    """The name of one training run of ``method`` (its artifact folder under ``methods/``): the method's own name
    for seed 0, the default run, and ``<method>-seed<k>`` for seed k (``make compare SEEDS=0,1,2``)."""
    return method if int(seed) == 0 else f"{method}-seed{int(seed)}"


def run_overrides(run: str) -> list[str]:
    """The overrides that select the training run folder ``run`` (:func:`method_run`'s inverse):
    ``["method=m"]`` for ``m``, ``["method=m", "seed=2"]`` for ``m-seed2``."""
    method, sep, seed = run.rpartition("-seed")
    if sep and seed.isdigit() and method:
        return [f"method={method}", f"seed={int(seed)}"]
    return [f"method={run}"]


def seed_problem(seed: object, key: str = "seed") -> str | None:
    """Why ``seed`` cannot seed a training run, or ``None`` when it can (a non-negative integer)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        return f"{key}={seed!r}: use a non-negative integer, e.g. seed=1"
    return None


@dataclass(frozen=True, order=True)
class Artifact:
    """One stage's artifact: shared by every method (``method=None``) or one method's own; of the run's
    subject (``subject=None``) or of another subject in the same outputs folder (a driver's ``fit``)."""

    stage: str
    method: str | None = None
    subject: str | None = None

    @property
    def id(self) -> str:
        """``stage`` or ``stage@method``: names its lock, temporary and scratch entries in its subject."""
        return self.stage if self.method is None else f"{self.stage}@{self.method}"

    @property
    def key(self) -> str:
        """How a reader's manifest names it among its inputs: ``id``, or ``subject:id`` for another subject."""
        return self.id if self.subject is None else f"{self.subject}:{self.id}"


def outputs_problem(outputs: str | Path | None) -> str | None:
    """Why ``paths.outputs`` cannot hold artifacts (empty, a file, not writable, a place where no folder can be made,
    e.g. under ``/proc``), or ``None`` when it can. It makes and removes an empty folder in the nearest folder of
    ``outputs`` that exists to find out."""
    if outputs is None or not str(outputs).strip():
        return "paths.outputs is empty; set it to a folder, e.g. paths.outputs=outputs"
    path = Path(outputs).absolute()
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return (
            f"paths.outputs={outputs}: {existing} is a file, not a folder; point paths.outputs at a folder "
            f"(it is created if missing)"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        return (
            f"paths.outputs={outputs}: {existing} is not writable (read-only file system or no permission); "
            f"choose a writable folder, e.g. paths.outputs=$HOME/interactavatar-outputs"
        )
    probe = existing / f".outputs-probe-{uuid.uuid4().hex[:_UNIQUE_HEX]}"
    try:
        probe.mkdir()
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):  # a full disk: a cached run still runs, a stage says it
            return None
        return (
            f"paths.outputs={outputs}: no folder can be made in {existing} ({exc.strerror}); choose a writable "
            f"folder, e.g. paths.outputs=$HOME/interactavatar-outputs"
        )
    probe.rmdir()
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
        """Directory of a stage shared by every method."""
        return self.root / stage

    def artifact_dir(self, artifact: Artifact) -> Path:
        """Directory of ``artifact``: ``<stage>/``, or ``methods/<method>/<stage>/`` for a method's own (under
        its subject's folder when it names another subject)."""
        root = self._subject_root(artifact)
        if artifact.method is None:
            return root / artifact.stage
        return root / METHODS_DIR / artifact.method / artifact.stage

    def _subject_root(self, artifact: Artifact) -> Path:
        return self.root if artifact.subject in (None, self.subject) else self.root.parent / artifact.subject

    def method_artifacts(self, stage: str) -> list[Artifact]:
        """Every method's artifact of the per-method ``stage`` that has a directory, by method name."""
        root = self.root / METHODS_DIR
        if not root.is_dir():
            return []
        return [Artifact(stage, p.name) for p in sorted(root.iterdir()) if (p / stage).is_dir()]

    @property
    def _tmp_root(self) -> Path:
        return self.root / ".tmp"

    @contextmanager
    def lock(
        self, artifact: Artifact, reads: Sequence[Artifact], order: Sequence[str], timeout_s: float, write: bool = True
    ) -> Iterator[None]:
        """Write lock (``write=False``: a read lock) on ``artifact`` and read locks on the artifacts it ``reads``,
        across processes.

        While held, no other run can write ``artifact`` or replace any of ``reads``; other readers of ``reads``
        (and with ``write=False`` of ``artifact``) may run alongside. Locks are taken in ``order`` (the DAG's
        topological order of stage names; then by subject and method), so runs never deadlock, also when
        they read each other's subjects.
        """
        wanted = {a: True for a in reads} | {artifact: not write}
        rank = {name: i for i, name in enumerate(order)}
        ordered = sorted(wanted, key=lambda a: (rank[a.stage], a.subject or self.subject, a.method or ""))
        requests = [
            (self._lock_path(a), wanted[a], f"stage '{a.id}' of subject '{a.subject or self.subject}'") for a in ordered
        ]
        with flock_all(requests, timeout_s):
            yield

    def _lock_path(self, artifact: Artifact) -> Path:
        lock_dir = self._subject_root(artifact) / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        return lock_dir / f"{artifact.id}.lock"

    @contextmanager
    def key_lock(self, stage: str, key: str, timeout_s: float, on_wait: Callable[[], None]) -> Iterator[None]:
        """Exclusive lock on computing per-method ``stage`` with cache ``key`` for any method; calls
        ``on_wait`` once first if another run holds it (that run computes what this one would compute).

        Take it holding no lock, before the stage's own locks, and release it after them: a run waits for it
        holding nothing, so no run can deadlock with one that holds it."""
        lock_dir = self.root / ".locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        path, what = lock_dir / f"{stage}#{key[:_SCRATCH_KEY_HEX]}.lock", f"stage '{stage}' with key {key[:12]}"
        with ExitStack() as held:
            try:
                held.enter_context(flock(path, shared=False, timeout_s=0.0, what=what))
            except LockTimeout:
                on_wait()
                held.enter_context(flock(path, shared=False, timeout_s=timeout_s, what=what))
            yield

    @contextmanager
    def read_lock(self, artifact: Artifact) -> Iterator[None]:
        """A read lock on ``artifact`` if it is free now, else :class:`LockTimeout` at once (never waits)."""
        with flock(
            self._lock_path(artifact),
            shared=True,
            timeout_s=0.0,
            what=f"stage '{artifact.id}' of subject '{self.subject}'",
        ):
            yield

    def new_tmp_dir(self, artifact: Artifact) -> Path:
        """A fresh, empty directory for writing ``artifact``; call with its lock held."""
        self.discard_stale_tmp(artifact)
        path = self._tmp_root / f"{artifact.id}-{_unique()}"
        path.mkdir(parents=True)
        return path

    def discard_stale_tmp(self, artifact: Artifact) -> None:
        """Remove leftovers of killed runs of ``artifact`` (safe: the caller holds its lock), and only its own:
        ``evaluate@m-seed2-<id>`` belongs to method ``m-seed2``, which another run may be writing now."""
        _remove_own(self._tmp_root, artifact, rf"(old-)?[0-9a-f]{{{_UNIQUE_HEX}}}")

    def scratch_dir(self, artifact: Artifact, key: str) -> Path:
        """Persistent scratch space (checkpoints) of ``artifact`` for one cache ``key``.

        It survives a killed run so the next run with the same key can resume; a
        different key (config or inputs changed) never sees it.
        """
        path = self.root / ".scratch" / f"{artifact.id}-{key[:_SCRATCH_KEY_HEX]}"
        path.mkdir(parents=True, exist_ok=True)
        return path

    def discard_scratch(self, artifact: Artifact) -> None:
        """Remove every scratch dir of ``artifact`` (after it was published or found cached; lock held)."""
        _remove_own(self.root / ".scratch", artifact, rf"[0-9a-f]{{{_SCRATCH_KEY_HEX}}}")

    def discard_leftovers(self, artifact: Artifact) -> None:
        """Remove what killed or failed runs of ``artifact`` left behind (temporary dirs, checkpoints).

        Call with the artifact's write or read lock held (either keeps every writer out) and only when it
        is whole: no live run can be writing either, and no later run can resume from them.
        """
        self.discard_stale_tmp(artifact)
        self.discard_scratch(artifact)

    def discard_empty_scratch(self, scratch: Path) -> None:
        """Remove ``scratch`` if the stage left nothing in it to resume from (after a failure): no file but the
        attempt record, in it or in the folders of its training runs. A checkpoint keeps it for the next run with the
        same key to resume from."""
        if not any(p.is_file() and p != scratch / ATTEMPT_FILE for p in scratch.rglob("*")):
            shutil.rmtree(scratch, ignore_errors=True)

    @staticmethod
    def begin_attempt(scratch: Path) -> float:
        """Record in ``scratch`` that a run of its stage starts now; return the seconds of earlier runs that this
        one resumes from (0 for a fresh start).

        An earlier run that was killed or failed left its checkpoints here and :data:`ATTEMPT_FILE` with its
        start time: the work it saved took from that start to the newest checkpoint's modification time (the
        steps after it are lost and redone, so they do not count), plus what that run itself carried from
        runs before it. With no checkpoint left nothing is reused and nothing is carried.
        """
        marker = scratch / ATTEMPT_FILE
        saved = [
            p.stat().st_mtime
            for p in scratch.rglob("*")
            if p.is_file()
            and ATTEMPT_FILE not in p.name
            and not any(part.endswith(".tmp") for part in p.relative_to(scratch).parts)
        ]
        carried = 0.0
        if saved and marker.exists():
            try:
                earlier = json.loads(marker.read_text())
                carried = max(0.0, max(saved) - float(earlier["start"])) + float(earlier["carried_s"])
            except (ValueError, KeyError, TypeError):  # a torn marker: the time is unknown, the checkpoint still good
                carried = 0.0
        tmp = marker.with_name(f".{ATTEMPT_FILE}.{_unique()}")
        try:
            tmp.write_text(json.dumps({"start": time.time(), "carried_s": carried}))
            os.replace(tmp, marker)
        except OSError:  # a full disk: leave no torn marker that would keep the scratch folder for good
            tmp.unlink(missing_ok=True)
            raise
        return carried

    def publish(self, artifact: Artifact, tmp_dir: Path) -> Path:
        """Move a completed ``tmp_dir`` to the artifact's final path, replacing any old version."""
        final = self.artifact_dir(artifact)
        final.parent.mkdir(parents=True, exist_ok=True)
        aside = None
        if final.exists() or final.is_symlink():  # a link the user made, dangling or not, is set aside too
            aside = self._tmp_root / f"{artifact.id}-old-{_unique()}"
            os.replace(final, aside)
        os.replace(tmp_dir, final)
        if aside is not None:
            _remove(aside)
        return final

    def link_copy(self, source: Artifact, tmp_dir: Path) -> None:
        """Fill the empty ``tmp_dir`` with hard links to every file of ``source`` (a copy where the file
        system cannot link). Safe because a published artifact is never written in place: a new version
        replaces the whole directory."""
        src = self.artifact_dir(source)
        for path in sorted(src.rglob("*")):
            target = tmp_dir / path.relative_to(src)
            if path.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(path, target)
            except OSError:
                shutil.copy2(path, target)


def _unique() -> str:
    """A fresh name part of ``_UNIQUE_HEX`` hex digits."""
    return uuid.uuid4().hex[:_UNIQUE_HEX]


def _remove_own(root: Path, artifact: Artifact, suffix: str) -> None:
    """Remove the entries ``<artifact.id>-<suffix>`` of ``root`` (``suffix`` a regex), and no other: a glob on
    ``<id>-*`` would also take those of an artifact whose id extends this one (method ``m`` and ``m-seed2``)."""
    if not root.is_dir():
        return
    own = re.compile(re.escape(artifact.id) + "-" + suffix)
    for p in root.glob(f"{glob.escape(artifact.id)}-*"):
        if own.fullmatch(p.name):
            _remove(p)


def _remove(path: Path) -> None:
    """Remove the folder ``path``, or the link ``path`` alone (a stage folder the user linked elsewhere: what it
    points at is not this run's to delete, and ``shutil.rmtree`` refuses a link, which then stayed for good)."""
    if path.is_symlink():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path, ignore_errors=True)
