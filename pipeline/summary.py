"""Plain-text tables printed at the end of a run."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pipeline.runner import StageReport


def format_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A left-aligned text table with a header rule."""
    cells = [[str(h) for h in headers]] + [[format_value(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_value(value: Any) -> str:
    """Floats to 4 significant digits, everything else as ``str``."""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def stage_table(reports: Sequence[StageReport]) -> str:
    """Per-stage decision, wall time and peak resident memory."""
    rows = [
        (
            r.stage,
            r.action,
            f"{r.wall_s:.2f}" if r.action == "run" else "-",
            f"{r.peak_rss_mb:.0f}" if r.action == "run" else "-",
            r.reason,
        )
        for r in reports
    ]
    return format_table(("stage", "decision", "wall s", "peak MB", "reason"), rows)


def metrics_table(reports: Sequence[StageReport]) -> str:
    """Every scalar metric the stages recorded, one row each."""
    rows = [(r.stage, k, v) for r in reports for k, v in sorted(r.metrics.items())]
    return format_table(("stage", "metric", "value"), rows) if rows else "(no metrics recorded)"
