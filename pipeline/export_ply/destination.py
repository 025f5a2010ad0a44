"""The folder an export writes (``--out``): where it may lie, what ``--overwrite`` may replace, and how it appears
whole or not at all.

The frames are written into a hidden folder beside ``--out``, ``.<name>.<12 hex digits>.partial``, which the export
holds locked (``flock`` on the folder) while it lives, and which is renamed into place when every file is written;
an earlier export is renamed aside (``.<name>.<same digits>.old``) first and removed after. What a killed export
leaves, a later export to the same place removes: every such folder that no live export holds.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.export_ply.options import ExportError
from pipeline.manifest import MANIFEST_NAME
from pipeline.workspace import METHODS_DIR

#: the record an export writes beside its PLY files
EXPORT_INFO = "export.json"
#: the hex digits naming one export's hidden folders
_TOKEN_HEX = 12
#: what only a subject's outputs folder holds: the runner's lock folder and the methods' artifacts
_SUBJECT_MARKS = (".locks", METHODS_DIR)


def check_destination(out: Path, overwrite: bool, subject_dir: Path) -> None:
    """Refuse an ``out`` inside a subject's outputs (the run's, ``subject_dir``, or any other), and one that exists
    unless ``overwrite`` and an earlier export wrote it (its :data:`EXPORT_INFO` lists every file in it)."""
    owner = owning_subject(out, subject_dir)
    if owner is not None:
        raise ExportError(
            f"--out {out}: inside {owner}, a subject's outputs, which the pipeline keeps (a file written there changes "
            "its artifacts, and the next run computes them again); choose a folder outside it"
        )
    if not os.path.lexists(out):
        return
    if not out.is_dir() or out.is_symlink():
        raise ExportError(f"--out {out}: exists and is not a folder; choose another")
    if not overwrite:
        raise ExportError(f"--out {out}: exists; pass --overwrite to replace an earlier export, or choose another")
    problem = _not_an_export(out)
    if problem is not None:
        raise ExportError(f"--out {out}: {problem}")


def owning_subject(folder: Path, subject_dir: Path) -> Path | None:
    """The subject's outputs folder that ``folder`` is or lies in (links resolved, whether or not ``folder`` exists),
    or ``None``: ``subject_dir``, or any folder above ``folder`` that holds a runner's lock folder or methods'
    artifacts, or a stage's artifact (its manifest)."""
    resolved, subject = folder.resolve(), subject_dir.resolve()
    if resolved.is_relative_to(subject):
        return subject
    for above in (resolved, *resolved.parents):
        if (above / MANIFEST_NAME).is_file():
            return above.parent
        if any((above / mark).is_dir() for mark in _SUBJECT_MARKS):
            return above
    return None


def _not_an_export(out: Path) -> str | None:
    """Why ``--overwrite`` may not replace the folder ``out``, or ``None``: it holds the record of an earlier export
    (:data:`EXPORT_INFO`, naming its files) and no file or folder that record does not name."""
    try:
        record = json.loads((out / EXPORT_INFO).read_text())
        files = set(record["files"]) if isinstance(record, dict) and "world_to_file" in record else None
    except (OSError, ValueError, KeyError, TypeError):
        files = None
    if files is None:
        return (
            f"not a folder an earlier export wrote (no {EXPORT_INFO} of one); --overwrite replaces only such a "
            "folder: choose another --out"
        )
    others = sorted(
        p.name for p in out.iterdir() if p.name != EXPORT_INFO and (p.name not in files or not _plain_file(p))
    )
    if others:
        return (
            f"holds {', '.join(others[:3])}{', ...' if len(others) > 3 else ''}, which the export there did not write "
            f"(its {EXPORT_INFO} lists its files); move them elsewhere first, or choose another --out"
        )
    return None


def _plain_file(path: Path) -> bool:
    return path.is_file() and not path.is_symlink()


@contextmanager
def partial_folder(out: Path) -> Iterator[Path]:
    """A new empty folder beside ``out`` (on its disk: renamed into place by :func:`publish`), held locked by this
    process for the ``with`` block and removed at its end (by then it is ``out`` where it was published). What killed
    exports to ``out`` left is removed first."""
    _check_parents(out)
    discard_leftovers(out)
    partial, fd = _held_partial(out)
    try:
        yield partial
    finally:
        shutil.rmtree(partial, ignore_errors=True)
        os.close(fd)


def _check_parents(out: Path) -> None:
    """Refuse an ``out`` under a file (it could never be made)."""
    blocker = next((p for p in (out.parent, *out.parent.parents) if os.path.lexists(p)), None)
    if blocker is not None and not blocker.is_dir():
        raise ExportError(f"--out {out}: {blocker} is not a folder; choose another place")


def _held_partial(out: Path) -> tuple[Path, int]:
    """(a new empty folder beside ``out``, the open descriptor of it that holds its lock)."""
    while True:
        partial = out.parent / f".{out.name}.{uuid.uuid4().hex[:_TOKEN_HEX]}.partial"
        try:
            partial.mkdir(parents=True)
        except OSError as exc:
            raise ExportError(write_problem(out, exc)) from exc
        fd = os.open(partial, os.O_RDONLY | os.O_DIRECTORY)
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            if os.path.samestat(os.fstat(fd), os.stat(partial)):
                return partial, fd
        except FileNotFoundError:
            pass  # another export took it for a killed one's between the mkdir and the lock, and removed it
        os.close(fd)


def discard_leftovers(out: Path) -> None:
    """Remove the hidden folders of exports to ``out`` that were killed: each ``.partial`` folder no live export holds,
    and the earlier export set aside with it (``.old``)."""
    if not out.parent.is_dir():
        return
    own = re.compile(re.escape(f".{out.name}.") + rf"([0-9a-f]{{{_TOKEN_HEX}}})\.(partial|old)")
    tokens = {match[1] for entry in out.parent.iterdir() if (match := own.fullmatch(entry.name))}
    for token in sorted(tokens):
        _discard_unless_held(out.parent / f".{out.name}.{token}.partial")


def _discard_unless_held(partial: Path) -> None:
    """Remove ``partial`` and its ``.old`` folder unless a live export holds ``partial``; holding its lock meanwhile,
    so that no export takes it up before it is gone."""
    try:
        fd: int | None = os.open(partial, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        fd = None  # published or removed: what is left is its earlier export, set aside
    try:
        if fd is not None:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        for folder in (partial, partial.with_suffix(".old")):
            shutil.rmtree(folder, ignore_errors=True)
    except BlockingIOError:
        pass  # a live export's
    finally:
        if fd is not None:
            os.close(fd)


def publish(partial: Path, out: Path) -> None:
    """Rename the finished ``partial`` folder to ``out``; an earlier export there is renamed aside first and removed
    after, so ``out`` holds the old export or the new one at every instant, also when this is interrupted."""
    if not os.path.lexists(out):
        partial.rename(out)
        return
    aside = partial.with_suffix(".old")
    out.rename(aside)
    try:
        partial.rename(out)
    except BaseException:
        aside.rename(out)
        raise
    shutil.rmtree(aside, ignore_errors=True)


def write_problem(out: Path, exc: OSError) -> str:
    """The one line for a write into ``out`` that failed with ``exc``: a full disk, or the system's reason."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return (
            f"--out {out}: no space left on its disk; free space there, or give --out on a larger disk (nothing "
            "was written)"
        )
    reason = exc.strerror or str(exc).rpartition(": ")[2]
    return f"--out {out}: cannot write there ({reason}); choose another folder (nothing was written)"
