"""Evaluate's wall time with the held-out motion tracked by the avatar, InteractAvatar against GaussianAvatars, for
one or more checkouts of the code.

``stage.evaluate.test_tracking=avatar`` refines every held-out frame's parameters with the trained model frozen
(``avatar/training/avatar_tracking.py``): tens of steps per frame, each posing the avatar and rendering the tuning
cameras. For InteractAvatar a pose also runs its networks (H, I, PointNet++), so the tracking costs it more than
GaussianAvatars, whose pose is the binding alone.

On a workspace trained until ``dynamic`` for both methods (made first with this checkout's code where it is missing),
the benchmark reruns ``evaluate`` alone (``run.only=evaluate run.force=true``) with each checkout's code, one
subprocess per run, on ``--threads`` threads. The runs are interleaved: each round runs every (checkout, method) once,
the order rotated from round to round, so that a change of the machine's load falls on all of them. Per checkout and
method it prints the medians over the rounds of evaluate's wall time (its manifest's), of the tracking's
(``tracking_seconds``) and of the 1-minute load average at the runs' starts; and, each taken per round (runs close in
time, so that a drift of the load cancels) and then its median, evaluate's time against GaussianAvatars' with the
same checkout and against the first checkout's with the same method.

A checkout is a folder holding the project's code (``label=path``): this one (the default), or another commit's from
a git worktree, whose compiled CPU rasterizer is taken from this checkout's build when it has none of its own. Every
checkout writes into the same workspace, so all of them evaluate the same trained models.

Usage:
    git worktree add /tmp/before <commit before the change>
    python benchmarks/bench_avatar_tracking.py --outputs /tmp/ws --preset smoke --rounds 3 \\
        --checkout before=/tmp/before --checkout after=.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.workspace import method_run  # noqa: E402

METHODS = ("interactavatar", "gaussian_avatars")
#: the compiled CPU rasterizer's build folder, relative to a checkout
EXTENSION_BUILD = Path("avatar/render/gaussians/csrc/build")


def _cli(checkout: Path, threads: int, *overrides: str) -> None:
    """One run of the ``interactavatar`` command (``pipeline.launch``) with ``checkout``'s code on ``threads`` threads
    (OMP_NUM_THREADS, which ``run.threads=auto`` follows), its output shown only when it fails."""
    command = [sys.executable, "-m", "pipeline.launch", "run.progress=false", *overrides]
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": str(threads)}
    done = subprocess.run(command, cwd=checkout, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stdout + done.stderr)[-4000:]
        sys.exit(f"{checkout}: {' '.join(command)} failed ({done.returncode}):\n{tail}")


def _with_extension(checkout: Path) -> None:
    """Give ``checkout`` this checkout's compiled rasterizer where it has none (a fresh worktree): otherwise
    ``backend=auto`` falls back to the torch rasterizer there and the comparison measures the rasterizers."""
    source, target = REPO / EXTENSION_BUILD, checkout / EXTENSION_BUILD
    if checkout.resolve() != REPO and source.is_dir() and not target.exists():
        shutil.copytree(source, target)


def _evaluate_manifest(outputs: Path, subject: str, method: str) -> dict:
    return json.loads((outputs / subject / "methods" / method_run(method) / "evaluate" / "_manifest.json").read_text())


def _trained(outputs: Path, subject: str, method: str) -> bool:
    return (outputs / subject / "methods" / method_run(method) / "dynamic" / "_manifest.json").is_file()


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, required=True, help="the workspace (paths.outputs); made if missing")
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--preset", default="smoke", help="quality= of the workspace (smoke, draft, ...)")
    parser.add_argument(
        "--checkout",
        action="append",
        default=None,
        help="label=path of a checkout to run evaluate with (repeatable; default: this one, 'this=.')",
    )
    parser.add_argument("--rounds", type=int, default=3, help="runs of every (checkout, method), interleaved")
    parser.add_argument("--threads", type=int, default=1, help="run.threads of every run")
    add_results_argument(parser)
    args = parser.parse_args()
    checkouts = {
        label: Path(path).resolve() for label, path in (c.split("=", 1) for c in (args.checkout or ["this=."]))
    }
    outputs = args.outputs.resolve()
    common = [f"paths.outputs={outputs}", f"subject={args.subject}", f"quality={args.preset}"]
    log = ResultLog("bench_avatar_tracking", preset=args.preset)
    for method in METHODS:  # the trained models every checkout evaluates, made with this checkout's code
        if not _trained(outputs, args.subject, method):
            print(f"training {method} until dynamic ({args.preset}) in {outputs}", flush=True)
            _cli(REPO, args.threads, *common, f"method={method}", "run.until=dynamic")
    for checkout in checkouts.values():
        _with_extension(checkout)
    runs = [(label, method) for label in checkouts for method in METHODS]
    wall: dict[tuple[str, str], list[float]] = {run: [] for run in runs}
    tracking: dict[tuple[str, str], list[float]] = {run: [] for run in runs}
    load: dict[tuple[str, str], list[float]] = {run: [] for run in runs}
    for r in range(args.rounds):
        shift = r % len(runs)
        for label, method in runs[shift:] + runs[:shift]:
            load[label, method].append(os.getloadavg()[0])
            started = time.monotonic()
            _cli(
                checkouts[label],
                args.threads,
                *common,
                f"method={method}",
                "run.only=evaluate",
                "run.force=true",
                "stage.evaluate.test_tracking=avatar",
            )
            metrics = _evaluate_manifest(outputs, args.subject, method)
            wall[label, method].append(float(metrics["timings"]["wall_s"]))
            tracking[label, method].append(float(metrics["metrics"]["tracking_seconds"]))
            print(
                f"round {r + 1}: {label} {method}: evaluate {wall[label, method][-1]:.1f} s, tracking "
                f"{tracking[label, method][-1]:.1f} s, load {load[label, method][-1]:.2f} "
                f"({time.monotonic() - started:.0f} s with the process)",
                flush=True,
            )
    first = next(iter(checkouts))
    rows = []
    for label, method in runs:
        ev, tr = _median(wall[label, method]), _median(tracking[label, method])
        # paired per round (runs close in time), then the median: a drift of the load cancels
        ratio = _median([a / b for a, b in zip(wall[label, method], wall[label, METHODS[1]])])
        speedup = _median([a / b for a, b in zip(wall[first, method], wall[label, method])])
        rows.append(
            [
                label,
                method,
                f"{ev:.1f}",
                f"{tr:.1f}",
                f"{ev - tr:.1f}",
                f"{ratio:.2f}",
                f"{speedup:.2f}",
                f"{_median(load[label, method]):.2f}",
            ]
        )
    title = (
        f"evaluate with stage.evaluate.test_tracking=avatar, {args.subject} at {args.preset}: medians of "
        f"{args.rounds} interleaved runs on {args.threads} thread(s); checkouts "
        + ", ".join(f"{label} ({_describe(path)})" for label, path in checkouts.items())
    )
    headers = (
        "checkout",
        "method",
        "evaluate s",
        "tracking s",
        "rest s",
        "evaluate / GaussianAvatars' (per round)",
        f"speed-up over {first} (per round)",
        "load (1 min)",
    )
    print(title)
    print(log.table(title, headers, rows))
    log.write(args.results)


def _describe(checkout: Path) -> str:
    """The commit a checkout is at (short hash; ``+changes`` where its tracked files differ from it)."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=checkout, capture_output=True, text=True)
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=checkout, capture_output=True)
    return (head.stdout.strip() or "unknown") + (" +changes" if dirty.returncode else "")


if __name__ == "__main__":
    main()
