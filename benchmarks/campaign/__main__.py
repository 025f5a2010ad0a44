"""``python -m benchmarks.campaign``: start, stop, watch or table the measurement campaign (see the package's
docstring)."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

from benchmarks.campaign.cells import Queue, QueueError, load_queue
from benchmarks.campaign.results import ResultFile
from benchmarks.campaign.runner import (
    REPO,
    AlreadyRunning,
    Options,
    Runner,
    lock_holder,
    lowest_priority_or_say,
    write_docs_pages,
)
from benchmarks.campaign.tables import render

QUEUE = REPO / "benchmarks" / "campaign" / "queue.toml"
OUTPUTS = REPO / "outputs" / "campaign"
PROG = "python -m benchmarks.campaign"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("command", choices=("start", "run", "stop", "status", "table"))
    p.add_argument("--queue", type=Path, default=QUEUE, help="the campaign's queue (default: %(default)s)")
    p.add_argument("--results", type=Path, help="the result file (default: benchmarks/results/<queue's result>.json)")
    p.add_argument("--outputs", type=Path, default=OUTPUTS, help="the runs' outputs folder (default: %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="cells at a time, one thread each (default: 1)")
    p.add_argument("--code", type=Path, help="run the code of this folder as it is (default: the newest commit)")
    p.add_argument("--launcher", help="the command that starts the app (default: this Python -m pipeline.launch)")
    p.add_argument("--no-commit", action="store_true", help="write the result file without committing it")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        queue = load_queue(args.queue)
    except QueueError as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        return 2
    results = (args.results or REPO / "benchmarks" / "results" / f"{queue.result}.json").resolve()
    outputs = args.outputs.resolve()
    lock = outputs / "runner.lock"
    if args.command == "table":
        text = render(queue, ResultFile(results).rows())
        print(text)
        results.with_suffix(".md").write_text(text + "\n")
        write_docs_pages(results)
        return 0
    if args.command == "status":
        return _status(queue, results, outputs, lock)
    if args.command == "stop":
        pid = lock_holder(lock)
        if pid is None:
            print(f"{PROG}: no runner works in {outputs}")
            return 0
        os.kill(pid, signal.SIGTERM)
        while lock_holder(lock) is not None:
            time.sleep(0.2)
        print(f"{PROG}: stopped the runner (pid {pid})")
        return 0
    if lock_holder(lock) is not None:
        print(f"{PROG}: a runner (pid {lock_holder(lock)}) already works in {outputs}", file=sys.stderr)
        return 1
    forwarded = [a for a in (argv if argv is not None else sys.argv[1:]) if a not in ("start", "run")]
    if args.command == "start" or os.getsid(0) != os.getpid():
        return _in_own_session(forwarded, outputs, background=args.command == "start")
    lowest_priority_or_say(print)
    options = Options(queue, results, outputs, code=args.code.resolve() if args.code else None, jobs=args.jobs)
    if args.launcher:
        options.launcher = tuple(shlex.split(args.launcher))
    options.commit = not args.no_commit
    runner = Runner(options)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda s, f: runner.stop())
    try:
        return runner.run()
    except AlreadyRunning as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        return 1


def _in_own_session(forwarded: list[str], outputs: Path, background: bool) -> int:
    """Run the runner in a session of its own (its own autogroup, whose nice it may lower without slowing this
    terminal): in the background with its lines in ``<outputs>/runner.log``, or in the foreground, waiting for it
    and passing Ctrl-C and SIGTERM on."""
    command = [sys.executable, "-m", "benchmarks.campaign", "run", *forwarded]
    outputs.mkdir(parents=True, exist_ok=True)
    if background:
        with open(outputs / "runner.log", "ab") as log:
            proc = subprocess.Popen(
                command, cwd=REPO, stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True
            )
        print(f"{PROG}: the runner (pid {proc.pid}) works in the background; its lines: {outputs / 'runner.log'}")
        print(f"{PROG}: `{PROG} status` shows where it is, `{PROG} stop` stops it")
        return 0
    proc = subprocess.Popen(command, cwd=REPO, start_new_session=True)

    def forward(signum: int, frame: FrameType | None) -> None:
        proc.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGINT, forward)
    signal.signal(signal.SIGTERM, forward)
    return proc.wait()


def _status(queue: Queue, results: Path, outputs: Path, lock: Path) -> int:
    finished = ResultFile(results)
    done = [c for c in queue.cells if finished.finished(c, queue.quality)]
    state_path = outputs / "state.json"
    state = json.loads(state_path.read_text()) if state_path.is_file() else {"in_progress": []}
    failed = json.loads((outputs / "failed.json").read_text()) if (outputs / "failed.json").is_file() else {}
    pid = lock_holder(lock)
    print(f"campaign {queue.result}: {len(done)} of {len(queue.cells)} cells finished ({results})")
    if pid is None:
        print(f"runner: not running (start it: {PROG} start)")
    else:
        try:
            prio = open(f"/proc/{pid}/autogroup").read().strip()
            nice = os.getpriority(os.PRIO_PROCESS, pid)
        except OSError:
            prio, nice = "?", "?"
        print(f"runner: pid {pid}, nice {nice}, {prio}; in progress: {', '.join(state['in_progress']) or '-'}")
    for key, info in failed.items():
        if not any(c.key == key for c in done):
            print(f"failed: {key} at {info['commit']} (exit {info['exit']}): {info['log']}")
    left = [c.key for c in queue.cells if c not in done and c.key not in state["in_progress"]]
    print(f"left: {len(left)}" + (f" (next: {left[0]})" if left else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
