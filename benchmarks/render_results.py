"""The pages generated from the committed benchmark results, so that nothing shown is typed by hand:

- the README's results table, from ``benchmarks/results/bench_seeds.json`` (written by ``bench_seeds.py
  table``), between ``<!-- results:begin -->`` and ``<!-- results:end -->``;
- ``docs/results/<name>.md``, one page per ``benchmarks/results/<name>.md`` (each written by its benchmark with
  the commit, machine, load and seeds), its plain-text tables fenced so they keep their columns;
- ``docs/results/<name>.md`` for every ``benchmarks/results/<name>.json`` written by
  ``benchmarks.provenance.ResultLog`` (runs with tables) that has no ``.md`` of its own: every run, newest first,
  with its commit, date, preset, seeds, machine, load and wall time, its tables as Markdown tables;
- ``docs/results/index.md`` listing them;
- from ``benchmarks/results/bench_make_run.json`` (written by ``bench_make_run.py``: what ``make run`` printed, its
  fit errors and wall time): the README's and ``docs/tutorials/first-run.md``'s printouts of the newest ``smoke``
  run (between ``<!-- make-run:begin -->`` and ``<!-- make-run:end -->``), first-run.md's fit errors (between
  ``<!-- make-run-fit:begin -->`` and ``<!-- make-run-fit:end -->``) and ``docs/reference/quality-presets.md``'s
  ``draft`` time from the newest ``draft`` run (between ``<!-- draft-time:begin -->`` and
  ``<!-- draft-time:end -->``).

``python benchmarks/render_results.py`` rewrites them; ``--check`` exits 1 if a committed page differs
(``tests/test_docs.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_seeds.json"
README = ROOT / "README.md"
DOCS_RESULTS = ROOT / "docs" / "results"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
MAKE_RUN = ROOT / "benchmarks" / "results" / "bench_make_run.json"
FIRST_RUN = ROOT / "docs" / "tutorials" / "first-run.md"
PRESETS = ROOT / "docs" / "reference" / "quality-presets.md"
PRINTOUT = ("<!-- make-run:begin -->", "<!-- make-run:end -->")
FIT_ERRORS = ("<!-- make-run-fit:begin -->", "<!-- make-run-fit:end -->")
DRAFT_TIME = ("<!-- draft-time:begin -->", "<!-- draft-time:end -->")
#: the settings the README shows (bench_seeds.py's docstring defines them), and its columns: (split, region, group)
SETTINGS = ("a", "b", "c", "d")
COLUMNS = (
    ("novel_view", "full", "all", "NV full"),
    ("novel_view", "hand", "all", "NV hand"),
    ("novel_view", "interaction", "contact", "NV contact"),
    ("self_reenact", "full", "all", "SR full"),
    ("self_reenact", "interaction", "contact", "SR contact"),
)


def _cell(row: dict) -> str:
    """The difference of the seed means with the larger seed standard deviation; bold where Welch's p < 0.05
    (and the difference is positive), WORSE where the full model is below by more than the spread."""
    text = f"{row['difference_db']:+.2f} ({row['larger_sd_db']:.2f})"
    if row["worse_beyond_spread"]:
        return f"WORSE {text}"
    return f"**{text}**" if row["welch_p"] < 0.05 and row["difference_db"] > 0 else text


def render(data: dict) -> str:
    """The Markdown block (markers included) for the results in ``data``."""
    rows = {(r["setting"], r["subject"], r["split"], r["region"], r["group"]): r for r in data["rows"]}
    lines = [
        BEGIN,
        "",
        "InteractAvatar's PSNR minus GaussianAvatars' in dB at `quality=draft` (mean over "
        "seeds; in brackets the larger of the two seed standard deviations; **bold**: Welch's p < 0.05; "
        "NV = held-out camera, SR = held-out motion, contact = the hand-face box in contact frames).",
        "",
        "| setting | subject | seeds | trained at | " + " | ".join(c[3] for c in COLUMNS) + " |",
        "| --- | --- | --- | --- | " + " | ".join("---" for _ in COLUMNS) + " |",
    ]
    for key, setting in data["settings"].items():
        name, subject = key.split("/")
        if name not in SETTINGS:
            continue
        cells = [_cell(rows[(name, subject, *c[:3])]) if (name, subject, *c[:3]) in rows else "-" for c in COLUMNS]
        lines.append(
            f"| ({name}) {setting['what']} | {subject} | {len(setting['seeds'])} | "
            f"`{setting['git'][:7]}` | " + " | ".join(cells) + " |"
        )
    lines += [
        "",
        f"Rendered from `benchmarks/results/bench_seeds.json` (table made at `{data['commit']}` on "
        f"{data['machine']}, {data['cores']} cores, load {data['load']}) by "
        "`python benchmarks/render_results.py`; per-region tables with LPIPS and Welch's p: "
        "`benchmarks/results/bench_seeds.md`.",
        "",
        END,
    ]
    return "\n".join(lines)


def replace_block(readme: str, block: str) -> str:
    """``readme`` with its results block replaced by ``block``."""
    start, end = readme.index(BEGIN), readme.index(END) + len(END)
    return readme[:start] + block + readme[end:]


def _fence_text_tables(text: str) -> str:
    """``text`` with every block (lines between blank lines) that holds a plain-text table (a ``----  ----``
    rule) put in a code fence, so that Markdown keeps its columns."""
    blocks = text.strip("\n").split("\n\n")
    rule = re.compile(r"^-{3,}(\s+-{3,})+\s*$", re.MULTILINE)
    return "\n\n".join(f"```\n{b}\n```" if rule.search(b) and not b.startswith("```") else b for b in blocks) + "\n"


def _cell_text(value: str) -> str:
    """A table cell's text, safe inside a Markdown table."""
    return value.replace("|", "\\|") or " "


def _markdown_table(columns: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(_cell_text(c) for c in columns) + " |", "|" + " --- |" * len(columns)]
    lines += ["| " + " | ".join(_cell_text(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


#: an issue reference in a title, e.g. " (issue 33)" or " (issue 35, part 3)": the project's history, which the
#: user's pages leave to docs/notes/ (tests/test_docs.py keeps them out)
_ISSUE_REFERENCE = re.compile(r"\s*\(issues? #?\d+[^)]*\)")


def _title(text: str) -> str:
    """``text`` as a title: without issue references and without a final full stop."""
    return _ISSUE_REFERENCE.sub("", text).strip().removesuffix(".")


def _titled(page: str) -> str:
    """A benchmark's Markdown ``page`` with its first heading as a title (:func:`_title`: no issue references)."""
    first, sep, rest = page.partition("\n")
    return (f"# {_title(first[2:])}" if first.startswith("# ") else first) + sep + rest


def _purpose(name: str) -> str:
    """The first sentence of ``benchmarks/<name>.py``'s docstring (its first paragraph up to the first full stop,
    so a summary that runs over two lines is not cut mid-sentence), as a title."""
    source = ROOT / "benchmarks" / f"{name}.py"
    doc = ast.get_docstring(ast.parse(source.read_text())) if source.is_file() else None
    if not doc:
        return name
    paragraph = " ".join(doc.split("\n\n", 1)[0].split())
    return _title(re.split(r"(?<=\.)\s", paragraph, maxsplit=1)[0])


def _trained_on(run: dict) -> str:
    """``trained on `cuda` (NVIDIA H100 ...); `` for a run that records its training device (bench_gpu), else
    nothing."""
    if "training_device" not in run:
        return ""
    gpu = f" (GPU: {run['gpu']})" if run.get("gpu") else ""
    return f"trained on `{run['training_device']}`{gpu}; "


def log_page(data: dict) -> str:
    """The page of a ``ResultLog`` file: every run, newest first, with where it came from and its tables."""
    name = data["benchmark"]
    lines = [
        f"# {name}: {_purpose(name)}",
        "",
        f"Written by `python benchmarks/{name}.py` (its arguments are given per run) into "
        f"`benchmarks/results/{name}.json`.",
        "",
    ]
    for run in reversed(data["runs"]):
        m = run["machine"]
        load = " ".join(f"{x:g}" for x in m["load"]) + " -> " + " ".join(f"{x:g}" for x in m["load_end"])
        preset = f", preset {run['preset']}" if run["preset"] else ""
        lines += [
            f"## {run['date']}, commit `{run['commit']}`{preset}",
            "",
            _trained_on(run)
            + f"{m['cpu']}, {m['cores']} cores, load {load}; {run['wall_s']:g} s"
            + (f"; seeds {', '.join(map(str, run['seeds']))}" if run["seeds"] else "")
            + f"; arguments: `{' '.join(run['argv']) or '(defaults)'}`",
            "",
        ]
        for table in run["tables"]:
            lines += [f"**{table['title']}**", "", _markdown_table(table["columns"], table["rows"]), ""]
    return "\n".join(lines)


def results_pages() -> dict[Path, str]:
    """docs/results/<name>.md for every benchmarks/results/<name>.md, and for every ResultLog file without one;
    the index."""
    folder = ROOT / "benchmarks" / "results"
    sources = sorted(folder.glob("*.md"))
    banner = (
        "<!-- generated from benchmarks/results/{} by benchmarks/render_results.py: edit the benchmark, "
        "not this page -->\n\n"
    )
    pages = {DOCS_RESULTS / s.name: banner.format(s.name) + _fence_text_tables(_titled(s.read_text())) for s in sources}
    for path in sorted(folder.glob("*.json")):
        data = json.loads(path.read_text())
        if path.with_suffix(".md").is_file() or not isinstance(data, dict) or "benchmark" not in data:
            continue
        pages[DOCS_RESULTS / f"{path.stem}.md"] = banner.format(path.name) + log_page(data)
    lines = [
        "# Results",
        "",
        "Every page here is a benchmark's own result file (`benchmarks/results/<name>.md` or "
        "`<name>.json`, with its commit, machine, load and seeds), rendered by "
        "`benchmarks/render_results.py`. Dated analyses of them are in the notes.",
        "",
    ]
    titles = {p: text.split("\n\n", 1)[1].splitlines()[0].lstrip("# ").strip() for p, text in pages.items()}
    lines += [f"- [{p.stem}]({p.name}): {_title(titles[p].removeprefix(p.stem + ':'))}" for p in sorted(pages)]
    pages[DOCS_RESULTS / "index.md"] = "\n".join(lines) + "\n"
    return pages


def between(text: str, markers: tuple[str, str], content: str) -> str:
    """``text`` with what stands between its ``markers`` (kept) replaced by ``content``."""
    start, end = text.index(markers[0]) + len(markers[0]), text.index(markers[1])
    return text[:start] + content + text[end:]


def newest(data: dict, preset: str) -> dict | None:
    """The newest run of ``bench_make_run.json`` at ``preset``, if any."""
    return next((run for run in reversed(data["runs"]) if run["preset"] == preset), None)


def duration(seconds: float) -> str:
    """``61.4`` -> ``61 s``, ``723`` -> ``12 min 3 s``."""
    minutes, rest = divmod(round(seconds), 60)
    return f"{minutes} min {rest} s" if minutes else f"{rest} s"


def measured_on(run: dict) -> str:
    """The machine, its load and the rasterizer of a ``bench_make_run`` run, as words."""
    m = run["machine"]
    rasterizer = (
        "the compiled CPU rasterizer"
        if run["rasterizer"].startswith("compiled CPU rasterizer ready")
        else "the torch rasterizer (the compiled one was not built)"
    )
    return (
        f"{m['cores']} cores of an {m['cpu']}, load {m['load'][0]:g} at the start and {m['load_end'][0]:g} at the "
        f"end, with {rasterizer}; commit `{run['commit']}`, {run['date']}"
    )


def trimmed(lines: list[str], keep: set[int]) -> str:
    """The lines whose index is in ``keep``, each run of the others written as one ``...``."""
    out: list[str] = []
    for i, line in enumerate(lines):
        if i in keep:
            out.append(line)
        elif not out or out[-1] != "...":
            out.append("...")
    return "\n".join(out)


class Printout:
    """The parts of ``make run``'s printed summary: line indices of the decision lines, the stage table's header,
    rule and rows (by stage), the metrics table's header and rows (by (stage, metric)), and the result lines."""

    def __init__(self, stdout: str) -> None:
        self.lines = stdout.rstrip("\n").split("\n")
        self.decisions = [i for i, line in enumerate(self.lines) if line.startswith("[")]
        header = [i for i, line in enumerate(self.lines) if line.startswith("stage ")]
        self.stage_header, self.metrics_header = header[0], header[1]
        self.stages = self._rows(self.stage_header, lambda w: w[0])
        self.metrics = self._rows(self.metrics_header, lambda w: (w[0], w[1]))
        end = max([*self.metrics.values(), self.metrics_header + 1])
        self.results = [i for i in range(end + 1, len(self.lines)) if self.lines[i].strip()]

    def _rows(self, header: int, key: Callable[[list[str]], Any]) -> dict[Any, int]:
        rows, i = {}, header + 2
        while i < len(self.lines) and self.lines[i].strip():
            rows[key(self.lines[i].split())] = i
            i += 1
        return rows

    def block(self, keep: set[int]) -> str:
        return trimmed(self.lines, keep)


#: the rows of the printout the README shows (the rest is trimmed)
README_STAGES = ("fit", "dynamic")
README_METRICS = (("evaluate", "novel_view_psnr"), ("evaluate", "self_reenact_psnr"))
#: the metrics rows first-run.md shows, beside the whole stage table
FIRST_RUN_METRICS = (
    ("fit", "train_mpjpe_hand_mm"),
    ("fit", "train_mpjpe_face_mm"),
    ("pbd", "gt_vertex_error_mm"),
    ("pbd", "zero_offset_error_mm"),
    ("dynamic", "ms_per_step"),
    ("evaluate", "novel_view_psnr"),
    ("evaluate", "novel_view_lpips"),
    ("evaluate", "self_reenact_psnr"),
    ("evaluate", "self_reenact_lpips"),
    ("reenact", "frames_per_second"),
    ("viewer", "mb_per_100_frames"),
)


def source(arguments: str = "") -> str:
    """Where a make-run figure comes from, as words."""
    return f"`benchmarks/results/bench_make_run.json`, written by `python benchmarks/bench_make_run.py{arguments}`"


def readme_printout(run: dict) -> str:
    """The README's block: the newest smoke run's printout, trimmed to a few lines of each part."""
    p = Printout(run["stdout"])
    keep = {p.decisions[0], p.decisions[-1], p.stage_header, p.stage_header + 1, p.metrics_header, *p.results}
    keep |= {p.stages[s] for s in README_STAGES if s in p.stages}
    keep |= {p.metrics[k] for k in README_METRICS if k in p.metrics}
    keep |= {i for i in range(len(p.lines)) if not p.lines[i].strip()}
    return (
        f"\nWhat `make run` (`quality=smoke`) printed on fresh outputs ({duration(run['app_wall_s'])} in all on "
        f"{measured_on(run)}; {source()}), trimmed:\n\n```\n{p.block(keep)}\n```\n"
    )


def first_run_printout(run: dict) -> str:
    """first-run.md's block: the newest smoke run's stage table whole, some metrics, the result lines."""
    p = Printout(run["stdout"])
    keep = {p.stage_header, p.stage_header + 1, *p.stages.values(), p.metrics_header, *p.results}
    keep |= {p.metrics[k] for k in FIRST_RUN_METRICS if k in p.metrics}
    keep |= {i for i in range(len(p.lines)) if not p.lines[i].strip()}
    end = trimmed(p.lines[p.stage_header :], {i - p.stage_header for i in keep})
    return (
        f"\nWhat `make run` prints at the end (`quality=smoke` on fresh outputs: {duration(run['app_wall_s'])} in "
        f"all on {measured_on(run)}; {source()}), trimmed where it says `...`:\n\n```\n{end}\n```\n"
    )


def fit_errors(run: dict) -> str:
    """first-run.md's fit errors: the training frames' hand MPJPE and face landmark error of the newest smoke run."""
    train = run["fit"]["train"]
    return (
        f"hand MPJPE {train['hand_mpjpe_mm']:.2f} mm and face landmarks {train['face_landmarks_mm']:.2f} mm on "
        f"`make run`'s training frames"
    )


def draft_time(run: dict | None) -> str:
    """quality-presets.md's paragraph on ``draft``'s wall time, from its newest run."""
    if run is None:
        return (
            "\n`draft`'s wall time is not in `benchmarks/results/bench_make_run.json` yet: "
            "`python benchmarks/bench_make_run.py --quality draft` measures it.\n"
        )
    wall = {r["stage"]: r["wall_s"] for r in run["reports"]}
    parts = (("dynamic", "stage two"), ("warmup", "the warm-up"), ("fit", "the fit"), ("capture", "the capture"))
    stages = ", ".join(f"{what} (`{s}`) {duration(wall[s])}" for s, what in parts if s in wall)
    return (
        f'\n`make run ARGS="quality=draft"` (the default method, InteractAvatar; every stage on fresh outputs, the '
        f"fit to the keypoints included) took {duration(run['app_wall_s'])} on {measured_on(run)}: {stages} "
        f"({source(' --quality draft')}).\n"
    )


def make_run_pages() -> dict[Path, str]:
    """The README's, first-run.md's and quality-presets.md's text rendered from bench_make_run.json."""
    data = json.loads(MAKE_RUN.read_text())
    smoke = newest(data, "smoke")
    if smoke is None:
        raise SystemExit(f"{MAKE_RUN} has no smoke run: run `python benchmarks/bench_make_run.py`")
    first_run = between(FIRST_RUN.read_text(), PRINTOUT, first_run_printout(smoke))
    return {
        README: between(README.read_text(), PRINTOUT, readme_printout(smoke)),
        FIRST_RUN: between(first_run, FIT_ERRORS, fit_errors(smoke)),
        PRESETS: between(PRESETS.read_text(), DRAFT_TIME, draft_time(newest(data, "draft"))),
    }


def rendered() -> dict[Path, str]:
    """Every generated file's path and the content it must have."""
    pages = make_run_pages()
    pages[README] = replace_block(pages[README], render(json.loads(RESULTS.read_text())))
    return {**pages, **results_pages()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a generated page differs from the data")
    args = parser.parse_args()
    pages = rendered()
    stale = [p for p, text in pages.items() if not p.is_file() or p.read_text() != text]
    if args.check:
        if stale:
            print("stale: " + ", ".join(str(p.relative_to(ROOT)) for p in stale))
        sys.exit(1 if stale else 0)
    DOCS_RESULTS.mkdir(parents=True, exist_ok=True)
    for path in stale:
        path.write_text(pages[path])
    print(f"rewrote {len(stale)} of {len(pages)} generated pages")


if __name__ == "__main__":
    main()
