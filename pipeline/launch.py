"""The ``interactavatar`` command's entry point. It imports the standard library only, then the app: a Ctrl-C
while Python still imports Hydra, torch and the pipeline (the command's first second or so) ends as one between
stages does, in one line and exit status 130, never in the traceback of whatever module was loading. Before it loads
anything that imports torch, it lets idle OpenMP threads sleep (:func:`pipeline.threads.wait_passively`), which the
OpenMP runtime reads only when it loads."""

from __future__ import annotations

from pipeline.exit_status import exit_interrupted_before_the_run  # the standard library only
from pipeline.threads import wait_passively  # the standard library only


def main() -> None:
    """Load :mod:`pipeline.cli` and run its ``main``; a Ctrl-C while it loads: one line on stderr, exit 130."""
    wait_passively()
    try:
        from pipeline.cli import main as run_command
    except KeyboardInterrupt:
        exit_interrupted_before_the_run()
    run_command()


if __name__ == "__main__":
    main()
