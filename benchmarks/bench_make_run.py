"""The printout, fit errors and wall time of `make run` on fresh outputs (at a preset: smoke, or draft).

It does what ``make run`` does after the install: ``make ext``'s check of the compiled CPU rasterizer, then
``interactavatar quality=<preset>`` (the default subject and method; ``run.progress=false`` so that no progress bar
is drawn; ``paths.outputs`` a fresh temporary folder, or ``--outputs``, which must not hold a run yet), and records
in ``benchmarks/results/bench_make_run.json`` (``--results``), with the commit, date, machine, load and preset that
every result file carries (``benchmarks/provenance.py``):

- ``stdout``: everything the app printed on its standard output, with the outputs folder written ``/…/outputs``
  (the decision lines, the stage table, the metrics table, the report's and the viewer's lines);
- ``reports``: each stage's decision, reason, wall time, peak memory and metrics, read back from the decision lines
  and the stages' manifests; ``pipeline.summary.stage_table`` and ``metrics_table`` of them give the printed tables
  again (the benchmark checks it, and so does ``tests/test_benchmark_results.py``, so a change of the formatter
  without a new run fails the tests);
- ``fit``: per sequence, the fit's hand MPJPE and face landmark error in mm (``fit/fit_report.json``);
- ``app_wall_s``: the app's wall time, start to exit.

``benchmarks/render_results.py`` renders the README's and ``docs/tutorials/first-run.md``'s printouts from the
newest ``smoke`` run, and ``docs/reference/quality-presets.md``'s ``draft`` time from the newest ``draft`` run.

Usage: python benchmarks/bench_make_run.py [--quality smoke] [--outputs DIR] [--results DIR] [override ...]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.runner import StageReport  # noqa: E402
from pipeline.summary import metrics_table, stage_table  # noqa: E402

NAME = "bench_make_run"
#: how the outputs folder is written in the stored printout (the README's way of eliding a user's own path)
OUTPUTS = "/…/outputs"
#: a decision line: ``[<subject>] <stage> <action> <reason>`` or ``[<subject>/<method>] ...`` (pipeline/runner.py)
DECISION = re.compile(
    r"^\[(?P<where>[^\]]+)\] (?P<stage>\S+) +(?P<action>would run|run|cached|shared|skip) +(?P<reason>.*)$"
)


def app_command() -> list[str]:
    """``interactavatar``, the console script beside this Python, else the same app as a module."""
    script = Path(sys.executable).parent / "interactavatar"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "pipeline.cli"]


def read_reports(stdout: str, outputs: Path) -> list[dict[str, Any]]:
    """Each stage's report as the app had it: decision and reason from its decision line, wall time, peak memory
    and metrics from the manifest the stage wrote (the values the runner reported)."""
    reports = []
    for line in stdout.splitlines():
        m = DECISION.match(line)
        if m is None:
            continue
        subject, _, method = m["where"].partition("/")
        folder = outputs / subject / ("methods/" + method if method else "") / m["stage"]
        manifest = json.loads((folder / "_manifest.json").read_text())
        ran = m["action"] == "run"
        reports.append(
            {
                "stage": m["stage"],
                "action": m["action"],
                "reason": m["reason"],
                "wall_s": manifest["timings"]["wall_s"] if ran else 0.0,
                "peak_rss_mb": manifest["peak_memory_mb"] if ran else 0.0,
                "metrics": manifest["metrics"],
            }
        )
    return reports


def stage_reports(stored: list[dict[str, Any]]) -> list[StageReport]:
    """The StageReport objects of stored reports."""
    return [StageReport(**r) for r in stored]


def printed_tables(stored: list[dict[str, Any]]) -> str:
    """The stage table and the metrics table as the app prints them (``pipeline/cli.py``'s ``run_app``) for the
    stored reports."""
    reports = stage_reports(stored)
    return f"\n{stage_table(reports)}\n\n{metrics_table(reports)}\n"


def fit_errors(outputs: Path, subject: str) -> dict[str, dict[str, float]]:
    """Per sequence, the fit's hand MPJPE and face landmark error in mm (``fit/fit_report.json``)."""
    report = json.loads((outputs / subject / "fit" / "fit_report.json").read_text())
    return {
        name: {"hand_mpjpe_mm": seq["mpjpe_hand_mm"], "face_landmarks_mm": seq["mpjpe_face_mm"]}
        for name, seq in report["sequences"].items()
    }


def rasterizer() -> str:
    """``make ext``'s check of the compiled CPU rasterizer (built if missing), its one line (paths in the
    checkout relative to it)."""
    done = subprocess.run(
        [sys.executable, "-c", "from avatar.render.gaussians.extension import main; main()"],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    return (done.stdout.strip().splitlines() or [done.stderr.strip()])[-1].replace(f"{REPO}/", "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quality", default="smoke", help="the preset (make run's default: smoke)")
    parser.add_argument("--outputs", type=Path, default=None, help="run here (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, as in make run's ARGS")
    add_results_argument(parser)
    args = parser.parse_args()
    ext = rasterizer()
    print(ext, flush=True)
    with tempfile.TemporaryDirectory(prefix="make-run-") as tmp:
        outputs = (args.outputs or Path(tmp) / "outputs").resolve()
        if outputs.exists() and any(outputs.iterdir()):
            sys.exit(f"{outputs} is not empty: bench_make_run measures a run on fresh outputs")
        command = [
            *app_command(),
            f"quality={args.quality}",
            "run.progress=false",
            f"paths.outputs={outputs}",
            *args.overrides,
        ]
        print("$ " + " ".join(command), flush=True)
        log = ResultLog(NAME, preset=args.quality)
        started = time.monotonic()
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
        app_wall_s = round(time.monotonic() - started, 1)
        sys.stdout.write(done.stdout)
        sys.stderr.write(done.stderr)
        if done.returncode != 0:
            sys.exit(f"the app exited with {done.returncode}; nothing recorded")
        stored = read_reports(done.stdout, outputs)
        if printed_tables(stored) not in done.stdout:
            sys.exit("the stage and metrics tables of the stored reports differ from what the app printed")
        subject = next(m for m in map(DECISION.match, done.stdout.splitlines()) if m)["where"].split("/")[0]
        fit = fit_errors(outputs, subject) if any(r["stage"] == "fit" for r in stored) else {}
        stdout = done.stdout.replace(str(outputs), OUTPUTS)
    text = log.table(
        "stages",
        ("stage", "decision", "wall s", "peak MB"),
        [(r["stage"], r["action"], f"{r['wall_s']:.2f}", f"{r['peak_rss_mb']:.0f}") for r in stored],
    )
    log.table(
        "fit errors (fit/fit_report.json)",
        ("sequence", "hand MPJPE mm", "face landmarks mm"),
        [(name, f"{e['hand_mpjpe_mm']:.2f}", f"{e['face_landmarks_mm']:.2f}") for name, e in fit.items()],
    )
    log.table("the app", ("wall s", "rasterizer"), [(f"{app_wall_s:.1f}", ext)])
    print(f"\n{text}\napp wall time {app_wall_s:.1f} s")
    path = log.write(args.results)
    data = json.loads(path.read_text())
    data["runs"][-1] |= {
        "command": " ".join(["interactavatar", *command[len(app_command()) :]]).replace(str(outputs), OUTPUTS),
        "rasterizer": ext,
        "app_wall_s": app_wall_s,
        "stdout": stdout,
        "reports": stored,
        "fit": fit,
    }
    path.write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
