"""The paper's Tables 1 and 2 on one capture: the comparison's rows per method, seed, split and region, mean and
spread over seeds, Welch's test against the full model, and the cost of each method's runs."""

from __future__ import annotations

from typing import Any

import numpy as np

from avatar.metrics.stats import welch_p
from data_schemas.metrics import COMPARISON, CONTACT_GROUPS, REGIONS, SPLITS
from pipeline.workspace import method_run
from reporting.method_runs import METRIC_NAMES, MethodRun

#: The tables a method can appear in (its YAML's ``method.tables``: table -> position in that table).
TABLES = ("baselines", "ablations")


def comparison_rows(runs: list[MethodRun]) -> dict[str, list]:
    """Columns of ``comparison.parquet``: one row per method, split, region and frame group with images."""
    rows: dict[str, list] = {c.name: [] for c in COMPARISON.columns}
    for run in runs:
        t = run.metrics
        for split in SPLITS:
            for region in REGIONS:
                for group in CONTACT_GROUPS:
                    sel = (t["split"] == split) & (t["region"] == region)
                    if group != "all":
                        sel &= t["contact"] == (group == "contact")
                    values = {
                        m: np.where(np.isinf(t[m][sel]), np.nan, t[m][sel]).astype(np.float64) for m in METRIC_NAMES
                    }
                    images = int(np.isfinite(values["ssim"]).sum())
                    if images == 0:
                        continue
                    for key, value in (
                        ("method", run.name),
                        ("seed", run.seed),
                        ("label", run.label),
                        ("split", split),
                        ("region", region),
                        ("contact", group),
                        ("images", images),
                        *((m, float(np.nanmean(values[m]))) for m in METRIC_NAMES),
                        ("train_steps", run.train_steps),
                        ("train_wall_s", run.train_wall_s),
                        ("gaussians", run.gaussians),
                    ):
                        rows[key].append(value)
    return rows


def seed_values(
    rows: dict[str, list], method: str, split: str, region: str, group: str = "all"
) -> dict[str, np.ndarray]:
    """metric -> (S,) the value of each seed's run of ``method`` (empty where it has no such row)."""
    found = [
        i
        for i in range(len(rows["method"]))
        if (rows["method"][i], rows["split"][i], rows["region"][i], rows["contact"][i])
        == (method, split, region, group)
    ]
    return {m: np.array([rows[m][i] for i in found], dtype=np.float64) for m in METRIC_NAMES}


def lookup(rows: dict[str, list], method: str, split: str, region: str, group: str = "all") -> dict[str, float]:
    """metric -> the mean over ``method``'s seeds (NaN where it has no row)."""
    return {
        m: float(np.nanmean(v)) if v.size and np.isfinite(v).any() else float("nan")
        for m, v in seed_values(rows, method, split, region, group).items()
    }


def seed_spread(values: np.ndarray) -> float:
    """Sample standard deviation (ddof 1) of the finite ``values``; NaN below two."""
    values = values[np.isfinite(values)]
    return float(np.std(values, ddof=1)) if values.size >= 2 else float("nan")


def run_cost(runs: list[MethodRun], shared: dict[str, dict[str, Any]]) -> dict[str, float]:
    """Wall time of the comparison as computed (shared stages and identical warm-ups once) and as it would be
    with every method computed from scratch."""
    shared_s = sum(float(m["timings"]["wall_s"]) for m in shared.values())
    warmups = {r.manifests["warmup"]["key"]: float(r.manifests["warmup"]["timings"]["wall_s"]) for r in runs}
    own = sum(float(r.manifests[s]["timings"]["wall_s"]) for r in runs for s in ("dynamic", "evaluate"))
    every = sum(float(r.manifests["warmup"]["timings"]["wall_s"]) for r in runs)
    return {
        "total_wall_s": shared_s + sum(warmups.values()) + own,
        "warmups_trained": len(warmups),
        "unshared_wall_s": len(runs) * shared_s + every + own,
    }


def fmt(value: float, digits: int) -> str:
    return "-" if not np.isfinite(value) else f"{value:.{digits}f}"


def metric_cells(values: dict[str, float]) -> list[str]:
    return [fmt(values["psnr"], 2), fmt(values["ssim"], 4), fmt(values["lpips"], 4)]


def stat_text(values: np.ndarray, digits: int) -> str:
    """The seeds' mean, with ``± standard deviation`` when there are two or more: ``31.12 ± 0.08``."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return "-"
    mean = fmt(float(finite.mean()), digits)
    return mean if finite.size < 2 else f"{mean} ± {seed_spread(finite):.{digits}f}"


def stat_cells(rows: dict[str, list], method: str, split: str, region: str, group: str = "all") -> list[str]:
    values = seed_values(rows, method, split, region, group)
    return [stat_text(values["psnr"], 2), stat_text(values["ssim"], 4), stat_text(values["lpips"], 4)]


#: the regions (and frame group) of the seeds table: where the full model's effects act
SEED_REGIONS = (("full", "all"), ("hand", "all"), ("face", "all"), ("interaction", "all"), ("interaction", "contact"))


SIGNIFICANCE = 0.05


def seed_table(rows: dict[str, list], present: dict[str, str], full: str, splits: list[str]) -> list[list[str]]:
    """Rows of the full model's PSNR minus each other method's (``present``: method -> label), per split and
    region: the difference of the means, the larger of the two seed spreads, Welch's p and what the seeds
    support."""
    out = []
    for split in splits:
        for method in present:
            if method == full:
                continue
            for region, group in SEED_REGIONS:
                a = seed_values(rows, full, split, region, group)["psnr"]
                b = seed_values(rows, method, split, region, group)["psnr"]
                if not (np.isfinite(a).any() and np.isfinite(b).any()):
                    continue
                diff = float(np.nanmean(a) - np.nanmean(b))
                spread = (
                    float(np.nanmax([seed_spread(a), seed_spread(b)])) if max(a.size, b.size) >= 2 else float("nan")
                )
                p = welch_p(a, b)
                verdict = (
                    "one seed: no spread"
                    if not np.isfinite(spread)
                    else "supported"
                    if np.isfinite(p) and p < SIGNIFICANCE
                    else "within the spread"
                )
                out.append(
                    [
                        split,
                        present[method],
                        region + (" (contact)" if group == "contact" else ""),
                        f"{diff:+.2f}",
                        fmt(spread, 2),
                        fmt(p, 3),
                        verdict,
                    ]
                )
    return out


def run_args(method: str, seed: int) -> str:
    """The command-line overrides that select one training run."""
    return f"method={method}" + (f" seed={seed}" if seed else "")


def comparison_tables(
    runs: list[MethodRun],
    rows: dict[str, list],
    missing: list[tuple[str, int]],
    cost: dict[str, float],
    stale: dict[str, tuple[str, str]] | None = None,
    corrupt: dict[str, tuple[str, str]] | None = None,
) -> dict[str, Any]:
    """The comparison as titled tables (headers, rows of strings) plus notes, for tables.md and the report.
    ``stale``, ``corrupt``: run -> (why, the overrides that select it). The notes' commands carry no run's
    command line (an artifact is a function of its cache key, which no command line is part of); the CLI prints
    the full commands after the run (``pipeline.cli``) and errors carry them (:func:`pipeline.config.fix_command`)."""
    command = lambda *args: " ".join(["interactavatar", *args])  # noqa: E731
    present = {r.name: r for r in runs}  # method -> one of its runs (label, ...)
    seeds = sorted({r.seed for r in runs})
    paper_cells = lambda m, split: metric_cells(paper) if (paper := present[m].paper(split)) else ["-"] * 3  # noqa: E731
    splits = [s for s in SPLITS if s in set(rows["split"])]
    in_table = {
        t: sorted(
            (m for m, r in present.items() if r.position(t) is not None), key=lambda m: (present[m].position(t), m)
        )
        for t in TABLES
    }
    full = min((m for m, r in present.items() if r.role.get("full_model")), default=None)
    table1 = [
        [split, present[m].label, *stat_cells(rows, m, split, "full"), *paper_cells(m, split)]
        for split in splits
        for m in in_table["baselines"]
    ]
    table2 = [
        [
            split,
            present[m].label,
            *(stat_text(seed_values(rows, m, split, region)["psnr"], 2) for region in ("full", "hand", "interaction")),
            *(stat_text(seed_values(rows, m, split, region)["lpips"], 4) for region in ("full", "hand", "interaction")),
            stat_text(seed_values(rows, m, split, "interaction", "contact")["psnr"], 2),
            *paper_cells(m, split),
        ]
        for split in splits
        for m in in_table["ablations"]
    ]
    budget = [
        [
            r.label,
            str(r.seed),
            str(r.train_steps),
            f"{r.train_wall_s:.0f}" + (" (resumed)" if r.resumed else ""),
            str(r.gaussians),
        ]
        for r in runs
    ]
    steps = {r.train_steps for r in runs}
    notes = [
        f"Training seeds: {', '.join(map(str, seeds))}. A cell is the mean over the seeds' runs, with ± the sample "
        "standard deviation (ddof 1) when there are two or more; each run's value is the mean over the frames of the "
        "split.",
        "Full images, mean over every frame of the split; PSNR in dB. Novel view: the held-out camera on the "
        "training motion; self-reenactment: the training cameras on the held-out motion; cross-reenactment "
        "(when reenact.driver names another subject): the training cameras on that subject's held-out motion "
        "transferred onto this one, against the synthetic ground truth of this identity performing it.",
        (
            "No method to compare yet."
            if not steps
            else "Every method trained the same number of optimisation steps (warm-up plus stage two: "
            f"{next(iter(steps))}) on the same frames and views."
            if len(steps) == 1
            else f"The methods trained different numbers of steps ({sorted(steps)}): the comparison is not fair."
        ),
        "Paper: InteractAvatar (ICCV 2025) on DECAF at 512x512; it gives no numbers for w/o PBD and w/o L_patch.",
        f"Cost: {cost['total_wall_s']:.0f} s of stage wall time as computed (shared stages once, "
        f"{cost['warmups_trained']:.0f} distinct warm-ups), against {cost['unshared_wall_s']:.0f} s with every "
        f"method computed from scratch.",
    ]
    if any(r.resumed for r in runs):
        notes.append(
            "Training seconds marked (resumed): the warm-up or stage two was killed and resumed from its "
            "checkpoint; the time counts the killed run up to its last checkpoint (the steps it lost after "
            "that were redone and count once)."
        )
    crossed = {
        r.label: r.manifests["evaluate"]["config"].get("reenact", {}).get("driver", "self")
        for r in runs
        if "cross_reenact" in set(r.metrics["split"])
    }
    if crossed:
        drivers = set(crossed.values())
        notes.append(
            f"Cross-reenactment driven by {', '.join(sorted(drivers))} ({', '.join(crossed)})"
            + ("" if len(drivers) == 1 else ": different drivers, the rows are not comparable")
            + "; "
            "methods evaluated without another subject as reenact.driver have no cross_reenact rows."
        )
    if missing:
        methods = ",".join(dict.fromkeys(m for m, _ in missing))
        missing_seeds = ",".join(dict.fromkeys(str(seed) for _, seed in missing))
        seeds_arg = [f"seed={missing_seeds}"] if missing_seeds != "0" else []
        notes.append(
            f"Not evaluated yet: {', '.join(method_run(m, seed) for m, seed in missing)}. Add them with "
            f"`{command('-m', f'method={methods}', *seeds_arg)}`, then `{command('run.only=compare')}`, with "
            "this comparison's paths.outputs, subject, preset and capture settings."
        )
    for run, (why, fix) in (corrupt or {}).items():
        notes.append(
            f"Left out, corrupted: {run}: {why} (`{command(*fix.split(), 'run.until=evaluate')}` recomputes it)."
        )
    for run, (why, fix) in (stale or {}).items():
        notes.append(
            f"Left out, stale: {run}: {why} (`{command(*fix.split(), 'run.until=evaluate')}`, "
            f"then `{command('run.only=compare')}`)."
        )
    return {
        "tables": [
            {
                "title": "Table 1: baselines against the full model (full image)",
                "headers": ["split", "method", "PSNR", "SSIM", "LPIPS", "paper PSNR", "paper SSIM", "paper LPIPS"],
                "rows": table1,
            },
            {
                "title": "Table 2: ablations per region (PSNR dB, then LPIPS)",
                "headers": [
                    "split",
                    "method",
                    "PSNR full",
                    "PSNR hand",
                    "PSNR interaction",
                    "LPIPS full",
                    "LPIPS hand",
                    "LPIPS interaction",
                    "PSNR interaction (contact frames)",
                    "paper PSNR",
                    "paper SSIM",
                    "paper LPIPS",
                ],
                "rows": table2,
            },
            {
                "title": "Training budget",
                "headers": ["method", "seed", "steps", "train wall s", "Gaussians"],
                "rows": budget,
            },
            *(
                [
                    {
                        "title": f"Seeds: {present[full].label}'s PSNR minus each method's (dB); 'supported' where "
                        f"Welch's t-test gives p < {SIGNIFICANCE} over the seeds",
                        "headers": [
                            "split",
                            "method",
                            "region",
                            "difference of means",
                            "larger seed sd",
                            "Welch p",
                            "seeds say",
                        ],
                        "rows": seed_table(rows, {m: r.label for m, r in present.items()}, full, splits),
                    }
                ]
                if full is not None and len(seeds) >= 2
                else []
            ),
        ],
        "notes": notes,
        "missing": missing,
    }


def markdown(tables: dict[str, Any]) -> str:
    out = ["# Methods side by side", ""]
    for table in tables["tables"]:
        out += [
            f"## {table['title']}",
            "",
            "| " + " | ".join(table["headers"]) + " |",
            "|" + "---|" * len(table["headers"]),
        ]
        out += ["| " + " | ".join(row) + " |" for row in table["rows"]]
        out.append("")
    out += [f"- {note}" for note in tables["notes"]]
    return "\n".join(out) + "\n"
