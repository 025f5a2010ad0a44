"""The campaign's result file (``benchmarks/results/<result>.json``): one record per finished cell, and the rows
that aggregate them over seeds.

Layout::

    {"campaign": "<result>",
     "cells": [{"setting", "subject", "method", "seed", "quality", "commit", "date", "machine", "threads",
                "wall_s", "load", "overrides", "train_steps", "train_wall_s", "gaussians",
                "metrics": [{"split", "region", "contact", "images", "psnr", "ssim", "lpips"}, ...]}, ...],
     "rows": [{"method", "subject", "setting", "quality", "split", "region", "contact",
               "seeds", "psnr", "ssim", "lpips", "commit"}, ...]}

A cell's metrics are the comparison stage's rows of its run (:func:`reporting.comparison_tables.comparison_rows`:
the mean over the split's images per region and frame group, ``contact`` being ``all``, ``contact`` or
``no_contact``). A row lists, per method, subject, setting, split, region and frame group, the value of every
finished seed (``psnr``, ``ssim``, ``lpips`` and the ``commit`` each seed was trained at, all in the order of
``seeds``). ``rows`` is derived from ``cells`` each time the file is written. Writes replace the file atomically:
a killed runner leaves the previous file or the next, never half of one.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from benchmarks.campaign.cells import Cell
from reporting.comparison_tables import comparison_rows
from reporting.method_runs import METRIC_NAMES, MethodRun

#: a row's key fields, in the order rows are sorted
ROW_KEY = ("setting", "subject", "method", "quality", "split", "region", "contact")
#: a cell's fields that come from the comparison rows of its run
METRIC_FIELDS = ("split", "region", "contact", "images", *METRIC_NAMES)


def cell_metrics(run: MethodRun) -> list[dict[str, Any]]:
    """The comparison's rows of one run (every split, region and frame group it has images of)."""
    rows = comparison_rows([run])
    return [{k: rows[k][i] for k in METRIC_FIELDS} for i in range(len(rows["method"]))]


class ResultFile:
    """The finished cells of a campaign, read from and written to one JSON file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.name = path.stem
        self.cells: list[dict[str, Any]] = []
        if path.is_file():
            try:
                data = json.loads(path.read_text())
                self.cells = list(data["cells"])
            except (OSError, ValueError, KeyError) as err:
                raise ValueError(
                    f"{path}: not a campaign result file ({err}); move it away or restore it with git"
                ) from None

    def finished(self, cell: Cell, quality: str) -> bool:
        """Whether ``cell`` has a record at ``quality``."""
        return any(_identity(c) == (*cell.identity(), quality) for c in self.cells)

    def add(self, record: dict[str, Any]) -> None:
        """Add a finished cell's record (replacing an earlier record of the same cell and quality)."""
        self.cells = [c for c in self.cells if _identity(c) != _identity(record)] + [record]

    def rows(self) -> list[dict[str, Any]]:
        """The cells' metrics aggregated over seeds (see the module's docstring), sorted by :data:`ROW_KEY`."""
        return aggregate(self.cells)

    def save(self) -> None:
        """Write the file atomically (a temporary file beside it, then renamed over it)."""
        data = {"campaign": self.name, "cells": self.cells, "rows": self.rows()}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        partial = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        partial.write_text(json.dumps(data, indent=1) + "\n")
        os.replace(partial, self.path)


def _identity(record: dict[str, Any]) -> tuple[str, str, str, int, str]:
    return (record["setting"], record["subject"], record["method"], int(record["seed"]), record["quality"])


def aggregate(cells: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per method, subject, setting, quality, split, region and frame group: the values of every seed."""
    grouped: dict[tuple, list[tuple[int, str, dict[str, Any]]]] = {}
    for cell in cells:
        for metric in cell["metrics"]:
            key = tuple(cell[k] if k in cell else metric[k] for k in ROW_KEY)
            grouped.setdefault(key, []).append((int(cell["seed"]), cell["commit"], metric))
    rows = []
    for key in sorted(grouped):
        seeds = sorted(grouped[key], key=lambda entry: entry[0])
        rows.append(
            {
                **dict(zip(ROW_KEY, key)),
                "seeds": [seed for seed, _, _ in seeds],
                **{m: [metric[m] for _, _, metric in seeds] for m in METRIC_NAMES},
                "commit": [commit for _, commit, _ in seeds],
            }
        )
    return rows
