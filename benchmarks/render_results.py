"""The pages generated from the committed benchmark results, so that nothing shown is typed by hand:

- the README's results table, from ``benchmarks/results/bench_seeds.json`` (written by ``bench_seeds.py
  table``), between ``<!-- results:begin -->`` and ``<!-- results:end -->``;
- ``docs/results/<name>.md``, one page per ``benchmarks/results/<name>.md`` (each written by its benchmark with
  the commit, machine, load and seeds), its plain-text tables fenced so they keep their columns;
- ``docs/results/<name>.md`` for every ``benchmarks/results/<name>.json`` written by
  ``benchmarks.provenance.ResultLog`` (runs with tables) that has no ``.md`` of its own: every run, newest first,
  with its commit, date, preset, seeds, machine, load and wall time, its tables as Markdown tables;
- ``docs/results/index.md`` listing them.

``python benchmarks/render_results.py`` rewrites them; ``--check`` exits 1 if a committed page differs
(``tests/test_docs.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_seeds.json"
README = ROOT / "README.md"
DOCS_RESULTS = ROOT / "docs" / "results"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
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


def _purpose(name: str) -> str:
    """The first sentence of ``benchmarks/<name>.py``'s docstring (its first paragraph up to the first full stop,
    so a summary that runs over two lines is not cut mid-sentence), as a title."""
    source = ROOT / "benchmarks" / f"{name}.py"
    doc = ast.get_docstring(ast.parse(source.read_text())) if source.is_file() else None
    if not doc:
        return name
    paragraph = " ".join(doc.split("\n\n", 1)[0].split())
    return _title(re.split(r"(?<=\.)\s", paragraph, maxsplit=1)[0])


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
            f"{m['cpu']}, {m['cores']} cores, load {load}; {run['wall_s']:g} s"
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
    pages = {DOCS_RESULTS / s.name: banner.format(s.name) + _fence_text_tables(s.read_text()) for s in sources}
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


def rendered() -> dict[Path, str]:
    """Every generated file's path and the content it must have."""
    readme = README.read_text()
    return {README: replace_block(readme, render(json.loads(RESULTS.read_text()))), **results_pages()}


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
