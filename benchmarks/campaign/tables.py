"""The campaign's tables in Markdown, from whatever cells are finished: per setting, subject and split, every method
of the queue with its seeds' mean and standard deviation, its difference to the first method of the queue (the
paper's InteractAvatar) with Welch's p, and the cells still missing marked as such."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from avatar.metrics.stats import welch_p
from benchmarks.campaign.cells import Queue
from benchmarks.provenance import commit, cpu_name

REPO = Path(__file__).resolve().parents[2]
#: (split, label) of the tables, and the PSNR columns: (region, frame group, label)
SPLITS = (("novel_view", "novel view (held-out camera)"), ("self_reenact", "self-reenactment (held-out motion)"))
COLUMNS = (
    ("full", "all", "full"),
    ("hand", "all", "hand"),
    ("face", "all", "face"),
    ("interaction", "contact", "interaction (contact frames)"),
)


def method_label(method: str) -> str:
    """The method's name in the paper's tables (``method.label`` of conf/method/<method>.yaml), else its name."""
    path = REPO / "conf" / "method" / f"{method}.yaml"
    try:
        return str(yaml.safe_load(path.read_text())["method"]["label"])
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        return method


def _values(rows: list[dict[str, Any]], key: dict[str, str], metric: str) -> tuple[np.ndarray, list[str]]:
    """(the seeds' values of ``metric`` in the row matching ``key``, the commits they were trained at)."""
    for row in rows:
        if all(row[k] == v for k, v in key.items()):
            return np.asarray(row[metric], dtype=np.float64), list(row["commit"])
    return np.zeros(0), []


def _stat(values: np.ndarray, digits: int) -> str:
    if not values.size:
        return "missing"
    text = f"{values.mean():.{digits}f}"
    return text + (f" ± {values.std(ddof=1):.{digits}f}" if values.size > 1 else "")


def render(queue: Queue, rows: list[dict[str, Any]]) -> str:
    """The Markdown page of the campaign's tables (``rows``: :meth:`ResultFile.rows`)."""
    expected: dict[tuple[str, str, str], int] = {}
    for cell in queue.cells:
        k = (cell.setting, cell.subject, cell.method)
        expected[k] = expected.get(k, 0) + 1
    finished = sum(1 for _ in {(r["setting"], r["subject"], r["method"], s) for r in rows for s in r["seeds"]})
    lines = [
        f"# {queue.result}: the measurement campaign's tables",
        "",
        f"Rendered at commit {commit()} on {cpu_name()}, {os.cpu_count()} cores, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, from benchmarks/results/{queue.result}.json: "
        f"{finished} of {len(queue.cells)} cells finished (quality={queue.quality}, one thread per run). Each value is "
        "the mean ± standard deviation over the finished seeds; `n` counts them against the seeds queued; "
        "`missing` marks a cell not measured yet. The difference is to the first method of each table (Welch's p "
        "where both have two seeds or more). `commits` lists the code each seed was trained at.",
        "",
    ]
    methods = queue.methods()
    for setting in queue.settings.values():
        subjects = list(dict.fromkeys(c.subject for c in queue.cells if c.setting == setting.name))
        for subject in subjects:
            listed = [m for m in methods if (setting.name, subject, m) in expected]
            lines += [
                f"## ({setting.name}) {subject}: {setting.what}",
                "",
                f"`quality={queue.quality} {' '.join(setting.overrides)}`",
                "",
            ]
            for split, split_label in SPLITS:
                lines += _split_table(rows, queue.quality, setting.name, subject, split, split_label, listed, expected)
    return "\n".join(lines)


def _split_table(
    rows: list[dict[str, Any]],
    quality: str,
    setting: str,
    subject: str,
    split: str,
    split_label: str,
    methods: list[str],
    expected: dict[tuple[str, str, str], int],
) -> list[str]:
    header = ["method", "n", *(f"PSNR {label}" for _, _, label in COLUMNS), "LPIPS full", "diff full (p)", "commits"]
    lines = [f"### {split_label}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    base = {"setting": setting, "subject": subject, "quality": quality, "split": split}
    reference, _ = _values(rows, {**base, "method": methods[0], "region": "full", "contact": "all"}, "psnr")
    for method in methods:
        key = {**base, "method": method}
        full, commits = _values(rows, {**key, "region": "full", "contact": "all"}, "psnr")
        psnr = [_stat(_values(rows, {**key, "region": r, "contact": g}, "psnr")[0], 2) for r, g, _ in COLUMNS]
        lpips = _stat(_values(rows, {**key, "region": "full", "contact": "all"}, "lpips")[0], 4)
        if method == methods[0] or not (full.size and reference.size):
            diff = "-"
        else:
            p = welch_p(full, reference)
            diff = f"{full.mean() - reference.mean():+.2f}" + (f" ({p:.3f})" if np.isfinite(p) else "")
        n = f"{full.size}/{expected[(setting, subject, method)]}"
        cells = [method_label(method), n, *psnr, lpips, diff, ", ".join(dict.fromkeys(commits)) or "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return [*lines, ""]
