"""The report's section on the methods side by side: the comparison's tables and the speed/quality front."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from data_schemas import web_escape as esc
from data_schemas.metrics import COMPARISON
from data_schemas.tables import read_table
from reporting.html import base64_file, figure_png, html_table, png_image, pyplot


def comparison_section(compare_dir: Path) -> str:
    """The compare stage's tables, notes and image rows."""
    tables = json.loads((compare_dir / "tables.json").read_text())
    parts = []
    for table in tables["tables"]:
        parts += [f"<h3>{esc.text(table['title'])}</h3>", html_table(tuple(table["headers"]), table["rows"])]
    parts.append("<ul>" + "".join(f"<li>{esc.text(note)}</li>" for note in tables["notes"]) + "</ul>")
    parts.append(pareto_plot(compare_dir))
    for figure in sorted((compare_dir / "figures").glob("*.png")):
        parts.append(
            f"<h3>{esc.text(figure.stem.replace('_', ' '))}: ground truth, then each method</h3>"
            + png_image(figure.stem, base64_file(figure))
        )
    return "\n".join(parts)


def pareto_front(cost: np.ndarray, quality: np.ndarray) -> np.ndarray:
    """(N,) bool: the points no other point beats, i.e. none is at most as costly and at least as good
    with one of the two strictly better. cost, quality: (N,)."""
    cost, quality = np.asarray(cost, float), np.asarray(quality, float)
    no_worse = (cost[None, :] <= cost[:, None]) & (quality[None, :] >= quality[:, None])
    better = (cost[None, :] < cost[:, None]) | (quality[None, :] > quality[:, None])
    return ~np.asarray((no_worse & better).any(axis=1))


def pareto_plot(compare_dir: Path) -> str:
    """Held-out quality against training time, one point per method of the comparison, the Pareto front
    joined (novel view and self-reenactment, full images, all frames)."""
    table = read_table(compare_dir / "comparison.parquet", COMPARISON)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), dpi=100)
    for ax, split in zip(axes, ("novel_view", "self_reenact")):
        rows = [
            i
            for i in range(len(table["method"]))
            if table["split"][i] == split and table["region"][i] == "full" and table["contact"][i] == "all"
        ]
        if not rows:
            continue
        cost = np.array([table["train_wall_s"][i] for i in rows], float)
        psnr = np.array([table["psnr"][i] for i in rows], float)
        front = pareto_front(cost, psnr)
        ax.scatter(cost, psnr, c=np.where(front, "tab:red", "tab:gray"))
        for i, c, q in zip(rows, cost, psnr):
            ax.annotate(str(table["label"][i]), (c, q), fontsize=8, xytext=(3, 3), textcoords="offset points")
        order = np.argsort(cost[front])
        ax.plot(cost[front][order], psnr[front][order], color="tab:red", linewidth=1)
        ax.set_xlabel("training wall time (s, warm-up + stage two)")
        ax.set_ylabel(f"{split.replace('_', ' ')} PSNR (dB)")
    png = figure_png(fig)
    return "<h3>Quality against training time (red: the Pareto front, methods no other beats on both)</h3>" + png_image(
        "quality against time", png
    )
