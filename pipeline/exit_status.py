"""The ``interactavatar`` command's exit status and line for a Ctrl-C, shared by its entry point
(:mod:`pipeline.launch`, standard library only) and the app (:mod:`pipeline.cli`)."""

from __future__ import annotations

import os
import sys
from typing import NoReturn

#: The exit status of a run stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED_STATUS = 130
INTERRUPTED_BETWEEN_STAGES = (
    "interrupted: the stages finished so far are kept and none was left half written; the same command goes on "
    "from there"
)


def exit_interrupted_before_the_run() -> NoReturn:
    """Say :data:`INTERRUPTED_BETWEEN_STAGES` and end the process with :data:`INTERRUPTED_STATUS`, for a Ctrl-C
    before any stage ran (Python importing the app, Hydra composing the config).

    The process ends with ``os._exit`` after flushing, not ``sys.exit``: a KeyboardInterrupt raised while an
    extension module's initialisation runs Python code through the C API marks it unhandled in CPython's runtime
    even when a handler up the stack catches it, and the interpreter then kills itself with SIGINT once it has
    finalised (the caller saw status -2 after this line, about once in 60 Ctrl-Cs in the first half second).
    Nothing that finalisation would do is owed here: no stage has run and nothing was written."""
    print(f"interactavatar: {INTERRUPTED_BETWEEN_STAGES}", file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(INTERRUPTED_STATUS)
