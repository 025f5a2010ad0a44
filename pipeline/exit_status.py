"""The ``interactavatar`` command's exit status and line for a Ctrl-C, shared by its entry point
(:mod:`pipeline.launch`, standard library only) and the app (:mod:`pipeline.cli`)."""

from __future__ import annotations

#: The exit status of a run stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED_STATUS = 130
INTERRUPTED_BETWEEN_STAGES = (
    "interrupted: the stages finished so far are kept and none was left half written; the same command goes on "
    "from there"
)
