"""A training step's cost when other jobs share the cores.

A smoke warm-up step and a stage-two step measured alone, beside one and beside two other smoke jobs, with this
checkout's code and (``--before DIR``) another checkout's; ``--one-thread`` adds this checkout with
``run.threads=1`` in every job (``after, 1``).

Every process here starts as a job of its code starts: with OMP_WAIT_POLICY, OMP_NUM_THREADS and MKL_NUM_THREADS
taken out of its environment (a command run by hand, a batch's job, a benchmark's run), then, where its code has
them, the thread settings of the ``interactavatar`` entry point and of a job's start (``pipeline.threads``: idle
OpenMP threads sleep, set before torch loads; ``run.threads`` once it has). The measured process trains
``--steps`` warm-up steps, then ``--steps`` stage-two steps of the full model, ``--rounds`` times, from the smoke
DAG's cached warm-up (``bench_dynamic.step_costs`` of its own code: the rounds alternate the two, medians); each
other job trains the same in a loop, and the measurement starts once every other job has finished its first round.
The scenarios are interleaved (each repeat: 0, 1, 2 other jobs, each with every code, in rotating order), run at
the caller's priority (``nice`` would change the sharing measured), and the tables give the medians over the
repeats, the ratio to the same code alone, the measured process's thread count, CPU seconds and context switches
(voluntary: it slept; involuntary: it was preempted), and the load average (1 min) when each measurement ended.
The smoke DAG is made first (``run.until=warmup``, at ``nice -n 10``) with this checkout's code, and one untimed
measurement per code builds its compiled rasterizer and warms the caches.

Usage: python benchmarks/bench_sharing.py [--before /tmp/before-threads] [--one-thread] [--others 0 1 2]
       [--repeats 2] [--steps 4] [--rounds 2] [--outputs DIR] [--results DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import select
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
#: the thread settings a process inherits from its caller's environment, which each process here starts without
THREAD_ENV = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
PRESET, SUBJECT = "smoke", "synth_a"
#: how long another job waits for its first round, and the longest it lives (it ends itself if the driver dies)
READY_TIMEOUT_S, JOB_LIFETIME_S = 600.0, 1800.0


# ---------------------------------------------------------------- the measured process and the other jobs


def start_like_a_job(code: Path, threads: str) -> Any:
    """Import ``code``'s project as a job of it starts with ``run.threads=threads`` (module docstring) and return its
    ``bench_dynamic``."""
    sys.path[:0] = [str(code), str(code / "benchmarks")]
    job_start = (code / "pipeline" / "threads.py").is_file()
    if job_start:
        from pipeline.threads import wait_passively

        wait_passively()  # what the entry point does before anything imports torch
    import bench_dynamic

    if job_start:
        from pipeline.threads import use_threads

        use_threads(threads)  # what a job does once its stages are loaded
    return bench_dynamic


def role_main(args: argparse.Namespace) -> None:
    """``--role measure``: one measurement, printed as a JSON line; ``--role job``: train in a loop until killed."""
    bench_dynamic = start_like_a_job(args.code.resolve(), args.threads)
    import torch

    if args.role == "job":
        parent, started = os.getppid(), time.monotonic()
        first = True
        while os.getppid() == parent and time.monotonic() - started < JOB_LIFETIME_S:
            bench_dynamic.step_costs(PRESET, SUBJECT, args.outputs, [], args.steps, 1)
            if first:
                print("ready", flush=True)
                first = False
        return
    start = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    costs = bench_dynamic.step_costs(PRESET, SUBJECT, args.outputs, [], args.steps, args.rounds)
    end = resource.getrusage(resource.RUSAGE_SELF)
    result = {
        "warmup_ms": costs["warmup_ms"],
        "stage_two_ms": costs["step_ms"],
        "threads": torch.get_num_threads(),
        "wait_policy": os.environ.get("OMP_WAIT_POLICY", "unset"),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": end.ru_utime + end.ru_stime - start.ru_utime - start.ru_stime,
        "voluntary": end.ru_nvcsw - start.ru_nvcsw,
        "involuntary": end.ru_nivcsw - start.ru_nivcsw,
    }
    print(json.dumps(result), flush=True)


# ---------------------------------------------------------------- the driver


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in THREAD_ENV}


def _role(role: str, code: Path, threads: str, outputs: Path, steps: int, rounds: int = 1) -> list[str]:
    return [
        sys.executable,
        str(Path(__file__).resolve()),
        "--role",
        role,
        "--code",
        str(code),
        "--threads",
        threads,
        "--outputs",
        str(outputs),
        "--steps",
        str(steps),
        "--rounds",
        str(rounds),
    ]


def _niced() -> None:
    os.nice(10)


def make_dag(outputs: Path) -> None:
    """The smoke DAG until the warm-up (cached when it is there), with this checkout's code, at nice 10."""
    command = [
        sys.executable,
        "-m",
        "pipeline.launch",
        f"quality={PRESET}",
        f"subject={SUBJECT}",
        f"paths.outputs={outputs}",
        "run.until=warmup",
        "run.progress=false",
        "fit.source=ground_truth",
    ]
    subprocess.run(command, cwd=REPO, env=_env(), check=True, preexec_fn=_niced, stdout=subprocess.DEVNULL)


def _wait_ready(jobs: list[subprocess.Popen[str]]) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    for job in jobs:
        assert job.stdout is not None
        while True:
            ready, _, _ = select.select([job.stdout], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                raise TimeoutError(f"another job did not finish its first round in {READY_TIMEOUT_S:.0f} s")
            line = job.stdout.readline()
            if line == "":
                raise RuntimeError(f"another job ended before its first round (exit {job.wait()})")
            if line.strip() == "ready":
                break


def measure(
    code: Path, threads: str, others: int, outputs: Path, steps: int, rounds: int, nice: bool = False
) -> dict[str, Any]:
    """One measurement with ``code`` and ``run.threads=threads`` beside ``others`` other jobs of the same code and
    setting: the measured process's JSON line, with the load average (1 min) when it ended."""
    jobs = [
        subprocess.Popen(
            _role("job", code, threads, outputs, steps),
            cwd=code,
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        for _ in range(others)
    ]
    try:
        _wait_ready(jobs)
        done = subprocess.run(
            _role("measure", code, threads, outputs, steps, rounds),
            cwd=code,
            env=_env(),
            capture_output=True,
            text=True,
            check=True,
            preexec_fn=_niced if nice else None,
        )
    finally:
        for job in jobs:
            job.terminate()
        for job in jobs:
            try:
                job.wait(timeout=30)
            except subprocess.TimeoutExpired:
                job.kill()
                job.wait()
    line = next(x for x in reversed(done.stdout.splitlines()) if x.startswith("{"))
    return json.loads(line) | {"load_1min": round(os.getloadavg()[0], 2)}


def role_parser() -> argparse.ArgumentParser:
    """The arguments of a measured process or another job (started by :func:`measure`)."""
    parser = argparse.ArgumentParser(description="one process of bench_sharing (started by it)")
    parser.add_argument("--role", choices=("measure", "job"), required=True)
    parser.add_argument("--code", type=Path, required=True)
    parser.add_argument("--threads", default="auto", help="run.threads (where the code has it)")
    parser.add_argument("--outputs", type=Path, required=True)
    parser.add_argument("--steps", type=int, required=True)
    parser.add_argument("--rounds", type=int, default=1)
    return parser


def main() -> None:
    if "--role" in sys.argv:  # a measured process or another job: nothing of this checkout is imported before
        role_main(role_parser().parse_args())
        return
    sys.path.insert(0, str(REPO))
    from benchmarks.provenance import ResultLog, add_results_argument

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, default=None, help="a checkout of the code before (git worktree add)")
    parser.add_argument("--others", type=int, nargs="+", default=[0, 1, 2], help="how many other jobs run beside")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved repeats of every scenario")
    parser.add_argument("--steps", type=int, default=4, help="warm-up and stage-two steps per round")
    parser.add_argument("--rounds", type=int, default=2, help="rounds per measurement (medians)")
    parser.add_argument(
        "--one-thread", action="store_true", help="also this checkout with run.threads=1 in every job ('after, 1')"
    )
    parser.add_argument("--outputs", type=Path, default=None, help="the smoke DAG here (default: a temp dir)")
    add_results_argument(parser)
    args = parser.parse_args()
    codes = {"after": (REPO, "auto")}
    if args.one_thread:
        codes["after, 1"] = (REPO, "1")
    if args.before is not None:
        codes["before"] = (args.before.resolve(), "auto")
    with tempfile.TemporaryDirectory() as tmp:
        outputs = (args.outputs or Path(tmp)).resolve()
        log = ResultLog("bench_sharing", preset=PRESET)
        make_dag(outputs)
        for code, _ in codes.values():  # untimed: builds the compiled rasterizer, warms the caches
            measure(code, "auto", 0, outputs, 1, 1, nice=True)
        runs: list[dict[str, Any]] = []
        for repeat in range(args.repeats):
            for others in args.others:
                order = list(codes.items())
                shift = (repeat + others) % len(order)
                for name, (code, threads) in order[shift:] + order[:shift]:
                    result = measure(code, threads, others, outputs, args.steps, args.rounds)
                    runs.append({"code": name, "others": others, "repeat": repeat} | result)
                    print(
                        f"{name:8s} beside {others}: warm-up {result['warmup_ms']:.0f} ms, stage two "
                        f"{result['stage_two_ms']:.0f} ms, {result['threads']} thread(s), load "
                        f"{result['load_1min']:.1f}",
                        flush=True,
                    )
        print()
        print(log.table(*summary(runs, codes, args)))
        print()
        print(log.table(*raw(runs)))
        log.write(args.results, runs=runs, codes={k: [str(c), t] for k, (c, t) in codes.items()})


def summary(runs: list[dict[str, Any]], codes: dict[str, tuple[Path, str]], args: argparse.Namespace) -> tuple:
    """The medians table: (title, headers, rows)."""
    rows = []
    for name in codes:
        alone = [r for r in runs if r["code"] == name and r["others"] == 0]
        base = {k: statistics.median(r[k] for r in alone) for k in ("warmup_ms", "stage_two_ms")} if alone else {}
        for others in args.others:
            mine = [r for r in runs if r["code"] == name and r["others"] == others]
            med = {
                k: statistics.median(r[k] for r in mine)
                for k in ("warmup_ms", "stage_two_ms", "cpu_s", "voluntary", "involuntary", "load_1min")
            }
            ratio = {k: f"{med[k] / base[k]:.1f}" if base else "-" for k in ("warmup_ms", "stage_two_ms")}
            rows.append(
                (
                    name,
                    others,
                    f"{mine[0]['threads']}, {mine[0]['wait_policy']}",
                    f"{med['warmup_ms']:.0f}",
                    ratio["warmup_ms"],
                    f"{med['stage_two_ms']:.0f}",
                    ratio["stage_two_ms"],
                    f"{med['cpu_s']:.1f}",
                    f"{med['voluntary']:.0f} / {med['involuntary']:.0f}",
                    f"{med['load_1min']:.1f}",
                )
            )
    title = (
        f"{PRESET} {SUBJECT}, ms per step beside other smoke jobs: medians of {args.repeats} interleaved repeats "
        f"of {args.rounds} rounds x {args.steps} steps each; x alone = the same code with no other job"
    )
    headers = (
        "code",
        "other jobs",
        "threads, wait policy",
        "warm-up ms",
        "x alone",
        "stage two ms",
        "x alone",
        "CPU s",
        "switches vol / invol",
        "load 1 min at end",
    )
    return title, headers, rows


def raw(runs: list[dict[str, Any]]) -> tuple:
    """Every measurement in the order run: (title, headers, rows)."""
    rows = [
        (
            r["repeat"],
            r["code"],
            r["others"],
            f"{r['warmup_ms']:.0f}",
            f"{r['stage_two_ms']:.0f}",
            f"{r['wall_s']:.1f}",
            f"{r['cpu_s']:.1f}",
            f"{r['load_1min']:.1f}",
        )
        for r in runs
    ]
    headers = ("repeat", "code", "other jobs", "warm-up ms", "stage two ms", "wall s", "CPU s", "load 1 min at end")
    return "every measurement, in the order run", headers, rows


if __name__ == "__main__":
    main()
