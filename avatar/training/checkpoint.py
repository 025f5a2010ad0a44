"""Checkpoints that are verified on load: a corrupt one is named, discarded, and never blocks a run.

File format: an 8-byte magic, the sha256 of the payload (32 bytes), then the
payload as written by ``torch.save``. Saving writes a temporary file, keeps the
previous checkpoint as ``<name>.prev`` and renames the new one into place, so a
kill at any instant leaves at least one whole checkpoint or none. Loading checks
the digest and the expected keys, and falls back from the newest checkpoint to
the previous one, then to nothing (start over), saying which file was discarded
and why.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch

MAGIC = b"IAVCKPT1"
_DIGEST_BYTES = 32
log = logging.getLogger(__name__)


def previous_path(path: Path) -> Path:
    """Where the checkpoint before ``path`` is kept."""
    return path.with_name(path.name + ".prev")


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` (tensors, numbers, strings, lists and dicts of them) to ``path`` atomically."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getvalue()
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(MAGIC + hashlib.sha256(payload).digest() + payload)
        f.flush()
        os.fsync(f.fileno())
    if path.exists():
        os.replace(path, previous_path(path))
    os.replace(tmp, path)


def discard_checkpoint(path: Path) -> None:
    """Delete the checkpoint at ``path`` and its previous one, where they are (a run that must not be resumed)."""
    for candidate in (path, previous_path(path)):
        candidate.unlink(missing_ok=True)


def placement(device: torch.device | str) -> Callable[[Any, str], Any] | None:
    """``torch.load``'s ``map_location`` for a run on ``device``: what was saved on any CUDA device goes to this one (a
    run resumed on another card of the machine, whose artifacts it shares), what was saved on the CPU stays there
    (the samplers' generator states); None on the CPU: every tensor where it was saved."""
    device = torch.device(device)
    if device.type != "cuda":
        return None
    index = device.index or 0
    return lambda storage, location: storage.cuda(index) if location.startswith("cuda") else storage


def _read(path: Path, required: Iterable[str], device: torch.device | str) -> dict[str, Any]:
    """The verified state in ``path``; ``ValueError`` saying what is wrong with it."""
    blob = path.read_bytes()
    head = len(MAGIC) + _DIGEST_BYTES
    if len(blob) < head or blob[: len(MAGIC)] != MAGIC:
        raise ValueError("not a checkpoint of this tool (bad header)")
    payload = blob[head:]
    if hashlib.sha256(payload).digest() != blob[len(MAGIC) : head]:
        raise ValueError("content does not match its digest (truncated or corrupted)")
    try:
        state = torch.load(io.BytesIO(payload), weights_only=True, map_location=placement(device))
    except Exception as exc:  # any unpickling failure means the file is unusable
        raise ValueError(f"unreadable ({type(exc).__name__}: {exc})") from exc
    missing = sorted(set(required) - set(state)) if isinstance(state, dict) else ["<a dict>"]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    return state


def load_checkpoint(path: Path, required: Iterable[str], device: torch.device | str = "cpu") -> dict[str, Any] | None:
    """The newest whole checkpoint at ``path`` (or its previous one), or ``None`` to start over; its tensors on the
    run's ``device`` (:func:`placement`).

    A checkpoint that fails verification is logged as a warning naming the file and
    the reason, and deleted, so it can never block a later run.
    """
    required = tuple(required)
    for candidate in (path, previous_path(path)):
        if not candidate.is_file():
            continue
        try:
            return _read(candidate, required, device)
        except (OSError, ValueError) as exc:
            log.warning(
                "%s: checkpoint discarded, %s; %s",
                candidate,
                exc,
                "trying the previous one" if candidate == path else "starting over",
            )
            candidate.unlink(missing_ok=True)
    return None
