"""``make bench``: every benchmark of ``benchmarks/``, each in its quick mode, one after the other; a failing
or timed-out benchmark is reported and the others still run. Ends with a table: benchmark, arguments, exit
status, wall time, and the machine's load.

Quick modes write under a temporary folder (``--keep DIR`` keeps it), never over the committed
``benchmarks/results/``. The benchmarks that read a finished run (``bench_reenact``, ``bench_viewer``, ``bench_refine``,
``bench_train_refine``, ``bench_test_tracking``, ``bench_avatar_tracking``) get one ``quality=smoke`` DAG made first.
``--full`` runs each with its own defaults instead (hours; those that need a run get the same smoke DAG, so pass a
bigger one by hand for real figures). A benchmark's full mode is always ``python benchmarks/<name>.py`` with its own
arguments (``--help``).

Usage: python benchmarks/run_all.py [--full] [--only bench_ssim bench_runner] [--timeout-s 900] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PY = sys.executable
#: benchmark -> its quick commands (argument lists, run in order); {out}: a scratch folder of its own, {smoke}: the
#: smoke DAG's outputs
QUICK: dict[str, list[list[str]]] = {
    "bench_ssim": [["--sizes", "64", "128", "--repeats", "3", "--results", "{out}"]],
    "bench_runner": [["--stages", "5", "--files", "10", "--kb", "64", "--skip-cli", "--results", "{out}"]],
    "bench_rasterizer": [["--quick", "--repeats", "2", "--threads", "1", "--no-memory", "--results", "{out}"]],
    "bench_fitting": [["--size", "96", "--frames", "4", "--results", "{out}"]],
    "bench_pbd": [["--sweeps", "50,100", "--tables", "1,2", "--results", "{out}"]],
    "bench_transfer": [["--results", "{out}"]],
    "bench_campaign_priority": [["--repeats", "1", "--busy", "1", "--tests", "tests/geometry", "--results", "{out}"]],
    "bench_seeds": [
        [
            "run",
            "--setting",
            "a",
            "--subject",
            "synth_a",
            "--seeds",
            "0",
            "1",
            "--quality",
            "smoke",
            "--outputs",
            "{out}",
        ],
        ["table", "--settings", "a", "--outputs", "{out}", "--results", "{out}"],
    ],
    "bench_small_captures": [
        ["run", "--pair", "e", "--seeds", "0", "--quality", "smoke", "--outputs", "{out}"],
        ["table", "--outputs", "{out}", "--results", "{out}"],
    ],
    "bench_heads": [
        [
            "cost",
            "--presets",
            "smoke",
            "--steps",
            "2",
            "--rounds",
            "1",
            "--outputs",
            "{out}",
            "--results",
            "{out}",
        ]
    ],
    "bench_scene": [["--preset", "smoke", "--scenes", "face_only", "--outputs", "{out}", "--results", "{out}"]],
    "bench_quality": [
        ["--presets", "smoke", "--methods", "gaussian_avatars", "--outputs", "{out}", "--results", "{out}"]
    ],
    "bench_dynamic": [
        [
            "--presets",
            "smoke",
            "--subjects",
            "synth_a",
            "--outputs",
            "{out}",
            "--cost-steps",
            "5",
            "--cost-rounds",
            "1",
            "--results",
            "{out}",
        ]
    ],
    "bench_patch_weight": [
        ["--preset", "smoke", "--weights", "0", "0.03", "--every", "50", "--outputs", "{out}", "--results", "{out}"]
    ],
    "bench_make_run": [["--results", "{out}"]],
    "bench_sharing": [
        ["--others", "0", "1", "--repeats", "1", "--steps", "2", "--rounds", "1", "--outputs", "{out}/sharing"]
        + ["--results", "{out}"]
    ],
    "bench_reenact": [["--outputs", "{smoke}", "--sizes", "128", "--repeats", "1", "--results", "{out}"]],
    "bench_viewer": [["--outputs", "{smoke}", "--frames", "2", "--play-s", "2", "--results", "{out}"]],
    "bench_refine": [
        [
            "--workspace",
            "{smoke}/synth_a",
            "--detector",
            "ground_truth",
            "--modes",
            "none",
            "silhouette",
            "--results",
            "{out}",
        ]
    ],
    "bench_train_refine": [
        ["--workspace", "{smoke}/synth_a", "--scales", "0", "3", "--steps", "50", "--results", "{out}"]
    ],
    "bench_test_tracking": [
        ["rates", "--workspace", "{smoke}/synth_a", "--frames", "2", "--sweep", "5x1", "--results", "{out}"]
    ],
    "bench_avatar_tracking": [["--outputs", "{smoke}", "--rounds", "1", "--results", "{out}"]],
    "bench_gpu": [
        [
            "--presets",
            "smoke",
            "--methods",
            "interactavatar",
            "--step-presets",
            "--skip-rasterizer",
            "--outputs",
            "{out}/work",
            "--results",
            "{out}",
        ]
    ],
}
#: the arguments a benchmark needs even in its full mode
NEEDS = {
    "bench_reenact": [["--outputs", "{smoke}"]],
    "bench_viewer": [["--outputs", "{smoke}"]],
    "bench_refine": [["--workspace", "{smoke}/synth_a"]],
    "bench_train_refine": [["--workspace", "{smoke}/synth_a"]],
    "bench_seeds": [["table"]],
    "bench_small_captures": [["table"]],
    "bench_test_tracking": [["rates", "--workspace", "{smoke}/synth_a"]],
    "bench_avatar_tracking": [["--outputs", "{smoke}"]],
}


def _cuda() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except ImportError:
        return False


def _smoke_dag(root: Path) -> Path:
    """A finished quality=smoke DAG (synth_a, the default method) under ``root``; its outputs folder."""
    outputs = root / "smoke"
    subprocess.run(
        [PY, "-m", "pipeline.cli", "quality=smoke", "run.progress=false", f"paths.outputs={outputs}"],
        cwd=REPO,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return outputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="each benchmark with its own defaults (hours)")
    parser.add_argument("--only", nargs="+", default=None, help="these benchmarks only")
    parser.add_argument("--timeout-s", type=float, default=900.0, help="per benchmark")
    parser.add_argument("--keep", type=Path, default=None, help="keep the scratch folders here")
    args = parser.parse_args()
    names = sorted(p.stem for p in (REPO / "benchmarks").glob("bench_*.py"))
    unknown = [n for n in names if n not in QUICK]
    if unknown:
        sys.exit(f"benchmarks without a quick mode in benchmarks/run_all.py: {unknown}")
    names = [n for n in names if args.only is None or n in args.only]
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench-"))
    root.mkdir(parents=True, exist_ok=True)
    smoke: Path | None = None
    rows = []
    for name in sorted(names, key=list(QUICK).index):
        if name == "bench_gpu" and not _cuda():
            rows.append((name, "", "skipped: no CUDA device here", "-"))
            continue
        commands = NEEDS.get(name, [[]]) if args.full else QUICK[name]
        if smoke is None and any("{smoke}" in a for command in commands for a in command):
            smoke = _smoke_dag(root)
        out = root / name
        out.mkdir(exist_ok=True)
        started, status = time.monotonic(), "ok"
        for command in commands:
            argv = [a.format(out=out, smoke=smoke) for a in command]
            print(f"== {name} {' '.join(argv)}", flush=True)
            try:
                done = subprocess.run([PY, f"benchmarks/{name}.py", *argv], cwd=REPO, timeout=args.timeout_s)
            except subprocess.TimeoutExpired:
                status = f"timed out after {args.timeout_s:.0f} s"
                break
            if done.returncode != 0:
                status = f"exit {done.returncode}"
                break
        rows.append((name, "; ".join(" ".join(c) for c in commands), status, f"{time.monotonic() - started:.0f}"))
    print("\n| benchmark | arguments | status | wall s |\n| --- | --- | --- | --- |")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print(
        f"\nload average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
        f"{os.cpu_count()} CPUs; scratch: {root if args.keep else 'removed'}"
    )
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    sys.exit(0 if all(r[2].startswith(("ok", "skipped")) for r in rows) else 1)


if __name__ == "__main__":
    main()
