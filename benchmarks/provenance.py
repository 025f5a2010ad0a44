"""Where a benchmark result came from (the commit and the machine), and :class:`ResultLog`, which writes a
benchmark's tables with it to ``benchmarks/results/<name>.json``."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pipeline.device import cpu_name
from pipeline.summary import format_table, format_value

REPO = Path(__file__).resolve().parent.parent


def commit() -> str:
    """``BENCH_COMMIT`` when set (a copy of the working tree sent to another machine, without its history), else
    the checkout's short commit, else ``unknown``."""
    if os.environ.get("BENCH_COMMIT"):
        return os.environ["BENCH_COMMIT"]
    try:
        proc = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    except OSError:
        return "unknown"
    return proc.stdout.strip() or "unknown"


def machine() -> dict[str, Any]:
    """The CPU model, its core count and the load average now (1, 5, 15 minutes)."""
    return {"cpu": cpu_name(), "cores": os.cpu_count(), "load": [round(x, 2) for x in os.getloadavg()]}


def add_results_argument(parser: argparse.ArgumentParser) -> None:
    """``--results DIR``: where the benchmark writes ``<name>.json`` (default: the committed
    ``benchmarks/results/``; ``make bench`` passes a scratch folder)."""
    parser.add_argument(
        "--results",
        type=Path,
        default=REPO / "benchmarks" / "results",
        help="write <benchmark>.json here (default: benchmarks/results/)",
    )


class ResultLog:
    """The tables one run of a benchmark prints, kept with where they came from and written as one more run of
    ``<results>/<name>.json``: ``{"benchmark": name, "runs": [run, ...]}``, each run holding ``commit``,
    ``date`` (UTC), ``machine`` (:func:`machine` at the start, ``load_end`` at the end), ``preset``, ``seeds``,
    ``wall_s``, ``argv`` and ``tables`` (each ``{"title", "columns", "rows"}``, rows as printed).
    ``benchmarks/render_results.py`` renders the file as ``docs/results/<name>.md``."""

    def __init__(self, name: str, *, preset: str | None = None, seeds: Sequence[int] = ()) -> None:
        self.name, self.preset, self.seeds = name, preset, list(seeds)
        self.started, self.machine = time.monotonic(), machine()
        self.date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        self.tables: list[dict[str, Any]] = []

    def table(self, title: str, headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
        """Record a table and return it as text (:func:`pipeline.summary.format_table`) to print."""
        self.tables.append(
            {
                "title": title,
                "columns": [str(h) for h in headers],
                "rows": [[format_value(c) for c in row] for row in rows],
            }
        )
        return format_table(headers, rows)

    def write(self, results: Path, **fields: Any) -> Path:
        """Append this run to ``results/<name>.json`` (created with its folder if missing), with ``fields`` (a GPU
        benchmark's ``training_device``, ``gpu``, its machine-readable ``figures``); the file's path."""
        results.mkdir(parents=True, exist_ok=True)
        path = results / f"{self.name}.json"
        data = json.loads(path.read_text()) if path.is_file() else {"benchmark": self.name, "runs": []}
        data["runs"].append(
            {
                "commit": commit(),
                "date": self.date,
                "machine": {**self.machine, "load_end": [round(x, 2) for x in os.getloadavg()]},
                "preset": self.preset,
                "seeds": self.seeds,
                "wall_s": round(time.monotonic() - self.started, 1),
                "argv": sys.argv[1:],
                "tables": self.tables,
                **fields,
            }
        )
        path.write_text(json.dumps(data, indent=1) + "\n")
        print(f"results: {path}")
        return path
