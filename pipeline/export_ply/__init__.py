"""interactavatar-export: every frame of a motion of a trained avatar as 3DGS PLY files, one per frame.

Not a stage: a reader of the artifacts of a finished run (the dynamic stage's model, the fit, the pbd stage's
offsets, the scene analysis); nothing is trained or re-run. A frame is posed exactly as the pipeline poses it:
a motion of the fit (the training motion as the method refined it, the held-out motion) as ``evaluate`` and the
viewer pose it, with the pbd stage's contact offsets when the method uses them; a params.parquet driver file as
``reenact`` drives the avatar with it (the motion transferred onto the subject, the contact simulated on its
face). The pose-dependent hand and the contact deformation are baked into each file.

Usage::

    interactavatar-export outputs/synth_a --motion test --out synth_a_test_ply
    interactavatar-export outputs/synth_a --motion driver/params.parquet --frames 0-9 --axes opengl --out clip

This module is the entry point, and imports the standard library only: a Ctrl-C or a SIGTERM while torch and the
core load ends in one line too. The work lies in :mod:`.options` (the command line), :mod:`.trained` (the run,
checked against its manifests and locked while it is read), :mod:`.frames` (posing and writing the frames),
:mod:`.destination` (the folder written) and :mod:`.command` (the command carried out, its errors in one line).
``export_frame``, ``export_motion``, ``open_run`` and ``trained_run`` are importable from here, loaded on first use.
"""

from __future__ import annotations

import importlib
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any

from pipeline.export_ply.options import LOCK_WAIT_S, PROG, parser

#: the exit status of an export stopped by Ctrl-C (128 + SIGINT) and by SIGTERM (128 + SIGTERM), as a shell reports it
INTERRUPTED_STATUS, TERMINATED_STATUS = 130, 143
#: the export's functions by the submodule that defines them (``__getattr__`` imports it on first use)
_API = {"export_frame": "frames", "export_motion": "frames", "open_run": "trained", "trained_run": "trained"}


class Terminated(BaseException):
    """SIGTERM arrived. Raised in the main thread like KeyboardInterrupt (not an ``Exception``, which code on the way
    could catch), so the export removes what it had begun on its way out."""


def main(argv: list[str] | None = None) -> int:
    """The command: 0 when the files are written; 2 with one line on stderr for a mistake; 130 (Ctrl-C) or 143
    (SIGTERM), one line, with nothing written."""
    args = parser().parse_args(argv)
    with _sigterm_raises():
        try:
            from pipeline.export_ply.command import run  # torch and the core: seconds

            return run(args, lock_wait_s=LOCK_WAIT_S)
        except KeyboardInterrupt:
            return _stopped("interrupted", args.out, INTERRUPTED_STATUS)
        except Terminated:
            return _stopped("terminated", args.out, TERMINATED_STATUS)


def _stopped(how: str, out: Path, status: int) -> int:
    print(f"{PROG}: {how}; nothing written to {out}", file=sys.stderr)
    return status


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` in the ``with`` block (in the main thread; elsewhere signals stay as they
    are), the handler it replaces restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _terminate(signum: int, frame: FrameType | None) -> None:
    """The SIGTERM handler: raise :class:`Terminated` once; a second SIGTERM cannot cut the clean-up short."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated


def __getattr__(name: str) -> Any:
    """``export_frame`` and the export's other functions (:data:`_API`), from their submodule."""
    if name not in _API:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_API[name]}"), name)
