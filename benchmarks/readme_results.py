"""The README's results table, rendered from ``benchmarks/results/bench_seeds.json`` (written by
``bench_seeds.py table``), so that the front door shows what the committed data says and nothing typed by hand.

The table sits between ``<!-- results:begin -->`` and ``<!-- results:end -->`` in README.md. ``python
benchmarks/readme_results.py`` rewrites it; ``--check`` exits 1 if the committed README differs
(``tests/test_docs.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_seeds.json"
README = ROOT / "README.md"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
#: the settings the README shows (bench_seeds.py's docstring defines them), and its columns: (split, region, group)
SETTINGS = ("a", "b", "c", "d")
COLUMNS = (("novel_view", "full", "all", "NV full"), ("novel_view", "hand", "all", "NV hand"),
           ("novel_view", "interaction", "contact", "NV contact"), ("self_reenact", "full", "all", "SR full"),
           ("self_reenact", "interaction", "contact", "SR contact"))


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
    lines = [BEGIN, "",
             "InteractAvatar's PSNR minus GaussianAvatars' in dB at `quality=draft` (mean over "
             "seeds; in brackets the larger of the two seed standard deviations; **bold**: Welch's p < 0.05; "
             "NV = held-out camera, SR = held-out motion, contact = the hand-face box in contact frames).", "",
             "| setting | subject | seeds | trained at | " + " | ".join(c[3] for c in COLUMNS) + " |",
             "| --- | --- | --- | --- | " + " | ".join("---" for _ in COLUMNS) + " |"]
    for key, setting in data["settings"].items():
        name, subject = key.split("/")
        if name not in SETTINGS:
            continue
        cells = [_cell(rows[(name, subject, *c[:3])]) if (name, subject, *c[:3]) in rows else "-" for c in COLUMNS]
        lines.append(f"| ({name}) {setting['what']} | {subject} | {len(setting['seeds'])} | "
                     f"`{setting['git'][:7]}` | " + " | ".join(cells) + " |")
    lines += ["", f"Rendered from `benchmarks/results/bench_seeds.json` (table made at `{data['commit']}` on "
                  f"{data['machine']}, {data['cores']} cores, load {data['load']}) by "
                  "`python benchmarks/readme_results.py`; per-region tables with LPIPS and Welch's p: "
                  "`benchmarks/results/bench_seeds.md`.", "", END]
    return "\n".join(lines)


def replace_block(readme: str, block: str) -> str:
    """``readme`` with its results block replaced by ``block``."""
    start, end = readme.index(BEGIN), readme.index(END) + len(END)
    return readme[:start] + block + readme[end:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if README.md's table differs from the data")
    args = parser.parse_args()
    readme = README.read_text()
    updated = replace_block(readme, render(json.loads(RESULTS.read_text())))
    if args.check:
        sys.exit(0 if updated == readme else 1)
    README.write_text(updated)
    print(f"README.md: results table {'unchanged' if updated == readme else 'rewritten'}")


if __name__ == "__main__":
    main()
