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


def test_every_benchmark_has_a_quick_mode() -> None:
    """``make bench`` refuses to start while a benchmark has none."""
    names = {p.stem for p in (REPO / "benchmarks").glob("bench_*.py")}
    assert names <= set(QUICK), sorted(names - set(QUICK))


def test_the_make_run_printout_on_file_is_what_the_summary_formatter_prints_for_its_reports() -> None:
    """The README and first-run.md show the newest smoke run of bench_make_run.json: its stage and metrics tables
    must be what pipeline.summary's formatters print today for the stage reports stored beside them, so a change of
    the formatter (or of the reports) without a new `python benchmarks/bench_make_run.py` fails here."""
    from benchmarks.bench_make_run import DECISION, printed_tables
    from benchmarks.render_results import MAKE_RUN, newest

    run = newest(json.loads(MAKE_RUN.read_text()), "smoke")
    assert run is not None, "bench_make_run.json has no smoke run"
    assert printed_tables(run["reports"]) in run["stdout"]
    decided = [m for m in map(DECISION.match, run["stdout"].splitlines()) if m]
    assert [(m["stage"], m["action"], m["reason"]) for m in decided] == [
        (r["stage"], r["action"], r["reason"]) for r in run["reports"]
    ]
    fit = next(r for r in run["reports"] if r["stage"] == "fit")["metrics"]
    assert set(run["fit"]) >= {"train", "test"}
    for sequence, errors in run["fit"].items():  # fit_report.json's errors are the fit stage's metrics
        assert errors == {
            "hand_mpjpe_mm": fit[f"{sequence}_mpjpe_hand_mm"],
            "face_landmarks_mm": fit[f"{sequence}_mpjpe_face_mm"],
        }
    assert sum(r["wall_s"] for r in run["reports"]) <= run["app_wall_s"] <= run["wall_s"]
    for key in ("commit", "date", "machine", "preset", "wall_s"):
        assert run[key], key


def test_the_printouts_in_the_readme_and_first_run_are_rendered_from_the_result_file() -> None:
    from benchmarks.render_results import FIRST_RUN, PRESETS, README, make_run_pages, trimmed

    assert trimmed(["a", "b", "c", "d", "e"], {0, 3}) == "a\n...\nd\n..."
    pages = make_run_pages()
    for path in (README, FIRST_RUN, PRESETS):
        assert pages[path] == path.read_text(), f"{path.name} is stale: run `python benchmarks/render_results.py`"
    readme, first_run = pages[README], pages[FIRST_RUN]
    for text in (readme, first_run):
        assert text.count("<!-- make-run:begin -->") == 1 and "evaluate   novel_view_psnr" in text
        assert "report: /…/outputs/synth_a/methods/interactavatar/report/report.html" in text
    assert "viewer     run" in first_run and "hand MPJPE" in first_run
    assert "<!-- draft-time:begin -->" in pages[PRESETS]
