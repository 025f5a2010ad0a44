"""What a background campaign costs the work in the foreground: a foreground job's time alone, beside busy jobs at the
campaign runner's priority, and beside the same jobs at a plain ``nice -n 15``.

The foreground job is a part of the test suite (``--tests``, default: a few fast folders; pytest, one process) run
at the caller's priority. The busy jobs, one per core (``--busy``), each multiply matrices on one thread for as long
as the foreground runs, in a session of their own as the runner's cells are, at one of two priorities:

- ``campaign``: :func:`benchmarks.campaign.priority.lowest_priority`, the runner's own call (its nice 19, SCHED_IDLE,
  and its autogroup's nice 19);
- ``nice 15``: their own nice 15 only, their autogroup left at 0 (what ``nice -n 15 cmd &`` from another terminal
  gives).

The three scenarios are interleaved (every repeat runs each, in rotating order); the table gives the foreground's
median wall time, its ratio to alone, the share of a core each busy job got meanwhile (its CPU time over the
foreground's wall time), and the load average. A campaign runner working on this machine meanwhile would be a fourth
party: the benchmark refuses to start while one holds outputs/campaign/runner.lock.

Usage: python benchmarks/bench_campaign_priority.py [--repeats 3] [--busy 2] [--tests tests/geometry ...]
       [--results DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.campaign.runner import lock_holder  # noqa: E402
from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402

TESTS = ("tests/geometry", "tests/pbd", "tests/metrics")
#: a busy job: one thread multiplying matrices until killed, at the priority its first argument names
BUSY = """\
import os, sys
os.environ["OMP_NUM_THREADS"] = "1"
if sys.argv[1] == "campaign":
    from benchmarks.campaign.priority import lowest_priority
    lowest_priority()
else:
    os.setpriority(os.PRIO_PROCESS, 0, 15)
import torch
torch.set_num_threads(1)
a = torch.randn(384, 384)
print("ready", flush=True)
while True:
    a = torch.tanh(a @ a)
"""
SCENARIOS = ("alone", "campaign", "nice 15")


def _cpu_s(pid: int) -> float:
    """User plus system CPU seconds of process ``pid`` so far (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(scenario: str, busy: int, tests: list[str]) -> tuple[float, float]:
    """(the foreground's wall seconds, the mean share of a core a busy job got meanwhile) in ``scenario``."""
    jobs = []
    if scenario != "alone":
        priority = "campaign" if scenario == "campaign" else "nice"
        for _ in range(busy):
            job = subprocess.Popen(
                [sys.executable, "-c", BUSY, priority],
                cwd=REPO,
                stdout=subprocess.PIPE,
                text=True,
                start_new_session=True,
                env={**os.environ, "PYTHONPATH": str(REPO)},
            )
            jobs.append(job)
        for job in jobs:
            assert job.stdout is not None and job.stdout.readline().strip() == "ready"
    try:
        before = [_cpu_s(j.pid) for j in jobs]
        started = time.monotonic()
        subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
            cwd=REPO,
            check=True,
            capture_output=True,
        )
        wall = time.monotonic() - started
        shares = [(_cpu_s(j.pid) - b) / wall for j, b in zip(jobs, before)]
    finally:
        for job in jobs:
            job.kill()
            job.wait()
    return wall, statistics.mean(shares) if shares else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--busy", type=int, default=os.cpu_count() or 2, help="busy jobs (default: one per core)")
    parser.add_argument("--tests", nargs="+", default=list(TESTS), help="the foreground's tests")
    add_results_argument(parser)
    args = parser.parse_args()
    holder = lock_holder(REPO / "outputs" / "campaign" / "runner.lock")
    if holder is not None:
        sys.exit(f"a campaign runner (pid {holder}) works here: stop it first (python -m benchmarks.campaign stop)")
    log = ResultLog("bench_campaign_priority")
    walls: dict[str, list[float]] = {s: [] for s in SCENARIOS}
    shares: dict[str, list[float]] = {s: [] for s in SCENARIOS}
    loads: dict[str, list[float]] = {s: [] for s in SCENARIOS}
    for repeat in range(args.repeats):
        order = SCENARIOS[repeat % 3 :] + SCENARIOS[: repeat % 3]
        for scenario in order:
            wall, share = measure(scenario, args.busy, args.tests)
            walls[scenario].append(wall)
            shares[scenario].append(share)
            loads[scenario].append(os.getloadavg()[0])
            print(f"repeat {repeat + 1}: {scenario:<8} {wall:6.1f} s, busy jobs {share:.0%} of a core each", flush=True)
    alone = statistics.median(walls["alone"])
    rows = [
        (
            scenario,
            args.busy if scenario != "alone" else 0,
            round(statistics.median(walls[scenario]), 1),
            round(statistics.median(walls[scenario]) / alone, 2),
            f"{statistics.median(shares[scenario]):.0%}" if scenario != "alone" else "-",
            round(statistics.median(loads[scenario]), 2),
        )
        for scenario in SCENARIOS
    ]
    title = f"the foreground ({' '.join(args.tests)}) beside busy jobs, medians of {args.repeats} interleaved repeats"
    print(
        log.table(
            title,
            ("busy jobs at", "busy jobs", "foreground s", "x alone", "core share per busy job", "load (1 min)"),
            rows,
        )
    )
    log.write(args.results)


if __name__ == "__main__":
    main()
