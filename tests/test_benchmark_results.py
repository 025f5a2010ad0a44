"""Benchmarks write their tables with where they came from (benchmarks/provenance.py ResultLog), and the docs'
results pages are rendered from those files (benchmarks/render_results.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from benchmarks.provenance import ResultLog
from benchmarks.render_results import log_page
from benchmarks.run_all import QUICK

REPO = Path(__file__).resolve().parent.parent


def test_a_result_log_appends_runs_with_commit_machine_preset_seeds_and_wall_time(tmp_path: Path) -> None:
    for seeds in ([0, 1], [2]):
        log = ResultLog("bench_example", preset="draft", seeds=seeds)
        text = log.table("speed", ("size", "ms"), [(64, 1.5), (128, 4.25)])
        assert "size" in text and "4.25" in text
        log.write(tmp_path)
    data = json.loads((tmp_path / "bench_example.json").read_text())
    assert data["benchmark"] == "bench_example" and [r["seeds"] for r in data["runs"]] == [[0, 1], [2]]
    run = data["runs"][-1]
    assert run["commit"] not in ("", "unknown") and run["preset"] == "draft" and run["wall_s"] >= 0
    assert run["machine"]["cores"] >= 1 and len(run["machine"]["load"]) == 3 and run["machine"]["cpu"]
    assert run["tables"] == [{"title": "speed", "columns": ["size", "ms"], "rows": [["64", "1.5"], ["128", "4.25"]]}]


def test_the_results_page_shows_every_run_newest_first_and_escapes_bars(tmp_path: Path) -> None:
    for value in ("old", "new"):
        log = ResultLog("bench_ssim")
        log.table("diff", ("max |rgb diff|",), [(value,)])
        log.write(tmp_path)
    page = log_page(json.loads((tmp_path / "bench_ssim.json").read_text()))
    assert page.startswith("# bench_ssim: D-SSIM training loss")  # the benchmark's own docstring
    assert page.index("| new |") < page.index("| old |")
    assert "| max \\|rgb diff\\| |" in page and page.count("## ") == 2


def test_a_benchmark_run_writes_its_rows_where_it_is_told(tmp_path: Path) -> None:
    subprocess.run(
        [
            sys.executable,
            "benchmarks/bench_runner.py",
            "--stages",
            "2",
            "--files",
            "2",
            "--kb",
            "1",
            "--skip-cli",
            "--results",
            str(tmp_path),
        ],
        cwd=REPO,
        check=True,
        capture_output=True,
    )
    run = json.loads((tmp_path / "bench_runner.json").read_text())["runs"][0]
    assert run["argv"][:2] == ["--stages", "2"] and len(run["tables"][0]["rows"]) == 1


def test_make_bench_sends_every_result_file_to_its_scratch_folder() -> None:
    """A quick mode must not append its numbers to the committed benchmarks/results/."""
    for name, commands in QUICK.items():
        source = (REPO / "benchmarks" / f"{name}.py").read_text()
        if "add_results_argument(parser)" in source or '"--results"' in source:
            assert any("--results" in command for command in commands), name
