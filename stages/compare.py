"""Stage ``compare``: the methods side by side (the paper's Tables 1 and 2 and its image rows on this capture).

Reads, for every method of ``stage.compare.methods`` that has been trained and evaluated on this subject
(``interactavatar -m method=...``), its ``evaluate`` metrics and renders and its ``warmup``/``dynamic`` run
records, and writes

- ``comparison.parquet`` (:data:`data_schemas.metrics.COMPARISON`): mean PSNR / SSIM / LPIPS per method,
  split, region and frame group (all, contact, no contact), with training steps, wall time and Gaussians;
- ``tables.json`` and ``tables.md``: Table 1 (baselines against the full model), Table 2 (ablations, per
  region), the paper's numbers beside ours, the training budget of every method (the fairness check) and
  the comparison's cost;
- ``figures/<split>_<hand|interaction>.png``: the ground truth and every method on the same contact frames,
  cropped to the hand box and to the hand-face overlap box (the paper's Figures 4, 5 and 7).

Listed methods that have not been evaluated yet are named in ``tables.md`` with the command that adds them;
the stage reruns when one appears (its digest enters the cache key). A method whose results were computed
from other inputs than the ones on disk now (:func:`stale_reason`: the capture, fit or PBD reran since, or
its own warm-up or stage two reran without its evaluation) is left out of every table and named, with the
reason, in the notes and the ``methods_stale`` metric: its row would compare results of different data.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from omegaconf import DictConfig

from avatar.metrics.stats import welch_p
from avatar.preprocess.crops import label_box, overlap_box
from data_schemas.capture import MASK_LABELS
from data_schemas.frames import crop_mask_path, rgb_path
from data_schemas.images import read_png, write_png
from data_schemas.metrics import COMPARISON, CONTACT_GROUPS, METRICS, REGIONS, SPLIT_SOURCES, SPLITS, showcase_path
from data_schemas.tables import read_table, write_table
from data_schemas.writes import write_bytes, write_json
from pipeline.config import fix_command, group_options
from pipeline.manifest import MANIFEST_NAME
from pipeline.stage import StageContext, stage
from pipeline.workspace import method_run

#: The tables a method can appear in (its YAML's ``method.tables``: table -> position in that table).
TABLES = ("baselines", "ablations")
#: The shared (not per-method) stages that ``evaluate`` reads; a method whose evaluation read other versions of them
#: is stale. Kept equal to the DAG's by ``tests/stages/test_compare.py`` (``scene`` was missing: issue 36, item 10).
SHARED_STAGES = ("capture", "frames", "fit", "scene", "pbd")
METRIC_NAMES = ("psnr", "ssim", "lpips")


@dataclass
class CompareConfig:
    """Types of ``stage.compare`` (values in conf/stage/compare.yaml)."""

    methods: list[str]
    seeds: list[int]
    crop_px: int


@dataclass
class MethodRun:
    """What the comparison reads of one training run of a method (one seed): its metrics table and run
    records."""

    name: str
    seed: int
    label: str
    evaluate_dir: Path
    metrics: dict[str, np.ndarray]
    manifests: dict[str, dict[str, Any]]  # warmup, dynamic, evaluate

    @property
    def run(self) -> str:
        """The run's folder name under ``methods/`` (:func:`pipeline.workspace.method_run`)."""
        return method_run(self.name, self.seed)

    @property
    def train_steps(self) -> int:
        return int(self.manifests["warmup"]["metrics"]["steps"]) + int(self.manifests["dynamic"]["metrics"]["steps"])

    @property
    def train_wall_s(self) -> float:
        """Wall time of the warm-up and stage two, without their validation passes (``validation_s``, when
        ``stage.<stage>.validation.every`` > 0): training, not measuring it. A stage resumed after a kill counts
        the earlier run's work it resumed from too (``timings.resumed_s``: up to that run's last checkpoint)."""
        stages = [self.manifests[s] for s in ("warmup", "dynamic")]
        return sum(
            float(m["timings"]["wall_s"])
            + float(m["timings"].get("resumed_s", 0.0))
            - float(m["metrics"].get("validation_s", 0.0))
            for m in stages
        )

    @property
    def resumed(self) -> bool:
        """Whether the warm-up or stage two resumed after a kill (its time partly estimated, see train_wall_s)."""
        return any("resumed_s" in self.manifests[s]["timings"] for s in ("warmup", "dynamic"))

    @property
    def gaussians(self) -> int:
        return int(self.manifests["dynamic"]["metrics"]["gaussians"])

    @property
    def role(self) -> dict[str, Any]:
        """The method's part in the comparison, from its own config as its evaluation recorded it (``method.tables``,
        ``method.full_model``, ``method.paper``: conf/method/<name>.yaml); empty for a method that declares none."""
        return self.manifests["evaluate"].get("config", {}).get("method", {})

    def position(self, table: str) -> int | None:
        """Where the method stands in ``table`` (:data:`TABLES`), or None when it is not in it."""
        value = (self.role.get("tables") or {}).get(table)
        return None if value is None else int(value)

    def paper(self, split: str) -> dict[str, float] | None:
        """The paper's (PSNR, SSIM, LPIPS) of this method for ``split``, when the paper gives them."""
        values = (self.role.get("paper") or {}).get(split)
        return None if values is None else dict(zip(METRIC_NAMES, map(float, values)))


def compare_checks(cfg: DictConfig) -> list[str]:
    """``stage.compare.methods`` naming a method the app does not have (no ``conf/method/<name>.yaml``), found
    before any stage runs rather than as a method never evaluated."""
    methods = [str(m) for m in cfg.stage.compare.methods]
    known = group_options("method")
    unknown = [m for m in methods if m not in known]
    if not unknown:
        return []
    return [f"stage.compare.methods={methods}: {unknown} are not methods; choose among {known} (conf/method/)"]


@stage(
    "compare",
    inputs=SHARED_STAGES,
    config_keys=("stage.compare",),
    outputs=("comparison.parquet", "tables.json", "tables.md", "figures"),
    config_schema=CompareConfig,
    cross_method_inputs=("warmup", "dynamic", "evaluate"),
    methods_key="stage.compare.methods",
    seeds_key="stage.compare.seeds",
    checks=compare_checks,
    reads_manifests=True,
    version="5",
)  # 5: resumed time; 4: scene; 3: seeds
def compare(ctx: StageContext) -> None:
    """Tables 1 and 2 and the image rows of the paper for every evaluated method of stage.compare.methods and
    training seed of stage.compare.seeds (mean and spread over the seeds)."""
    conf = ctx.cfg.stage.compare
    listed = [(str(m), int(seed)) for m in conf.methods for seed in conf.seeds]
    dirs = {stage: ctx.method_dirs(stage) for stage in ("warmup", "dynamic", "evaluate")}
    found = [
        _read_run(m, seed, {stage: dirs[stage][method_run(m, seed)] for stage in dirs})
        for m, seed in listed
        if all(method_run(m, seed) in dirs[stage] for stage in dirs)
    ]
    shared = {name: _manifest(ctx.input_dir(name)) for name in SHARED_STAGES}
    stale = {
        r.run: (why, _run_args(r.name, r.seed)) for r in found if (why := stale_reason(r.manifests, shared)) is not None
    }
    runs = [r for r in found if r.run not in stale]
    corrupt = {
        method_run(m, seed): (ctx.method_problems[method_run(m, seed)], _run_args(m, seed))
        for m, seed in listed
        if method_run(m, seed) in ctx.method_problems
    }
    command = functools.partial(fix_command, ctx.cfg)
    if not runs and (corrupt or stale):  # publishing would replace the last good comparison with an empty one
        raise RuntimeError(
            "nothing left to compare, so the last comparison is kept: "
            + "; ".join(
                f"{run} is {kind} ({why}): rerun it with `{command(*fix.split(), 'run.until=evaluate')}`"
                for kind, problems in (("corrupted", corrupt), ("stale", stale))
                for run, (why, fix) in problems.items()
            )
        )
    missing = [
        (m, seed)
        for m, seed in listed
        if method_run(m, seed) not in {r.run for r in found} and method_run(m, seed) not in corrupt
    ]
    rows = _comparison_rows(runs)
    write_table(
        ctx.out_dir / "comparison.parquet",
        COMPARISON,
        {c.name: (rows[c.name] if c.kind == "string" else np.asarray(rows[c.name])) for c in COMPARISON.columns},
    )
    cost = _cost(runs, shared)
    tables = _tables(runs, rows, missing, cost, stale, corrupt)  # artifacts hold no run's command line: see _tables
    write_json(ctx.out_dir / "tables.json", tables, "the comparison tables")
    write_bytes(ctx.out_dir / "tables.md", _markdown(tables).encode(), "the comparison tables")
    (ctx.out_dir / "figures").mkdir()
    first_seed = [r for r in runs if r.seed == int(conf.seeds[0])]  # the image rows: one run per method
    for split, sequence in _split_sequences(first_seed).items():
        for crop in ("hand", "interaction"):
            figure = _figure(first_seed, ctx.input_dir("frames"), split, sequence, crop, int(conf.crop_px))
            if figure is not None:
                write_png(ctx.out_dir / "figures" / f"{split}_{crop}.png", figure)
    ctx.metrics.update(
        {
            "methods_compared": len(runs),
            "methods_missing": ",".join(method_run(m, seed) for m, seed in missing) or "-",
            "methods_stale": ",".join(stale) or "-",
            "methods_corrupt": ",".join(corrupt) or "-",
            "seeds": ",".join(str(int(seed)) for seed in conf.seeds),
            "same_train_steps": int(len({r.train_steps for r in runs}) <= 1),
            **cost,
        }
    )


def _split_sequences(runs: list[MethodRun]) -> dict[str, str]:
    """split -> the capture sequence it renders, from the methods' ``splits.json`` (the fixed two splits for
    evaluations written before it existed)."""
    out = {split: sequence for split, (sequence, _) in SPLIT_SOURCES.items()}
    for run in runs:
        path = run.evaluate_dir / "splits.json"
        if path.is_file():
            out |= json.loads(path.read_text())
    return out


def _manifest(stage_dir: Path) -> dict[str, Any]:
    return json.loads((stage_dir / MANIFEST_NAME).read_text())


def stale_reason(manifests: dict[str, dict[str, Any]], shared: dict[str, dict[str, Any]]) -> str | None:
    """Why a method's results do not belong in this comparison, or None when they do.

    ``manifests``: the method's warmup, dynamic and evaluate manifests; ``shared``: the manifests of the shared
    stages this comparison reads (:data:`SHARED_STAGES`). A method's artifacts stay on disk when a shared
    stage reruns (another preset or capture in the same outputs folder, a changed fit), and its warm-up,
    stage two and evaluation can each be rerun alone: its row belongs here only if its evaluation read
    these shared stages' outputs and the chain warm-up -> stage two -> evaluation is one run (each read the
    outputs of the one before it that are on disk now).
    """
    reads = [("evaluate", name, shared[name]) for name in SHARED_STAGES]
    reads += [("evaluate", "dynamic", manifests["dynamic"]), ("dynamic", "warmup", manifests["warmup"])]
    for reader, name, manifest in reads:
        if manifests[reader].get("upstream", {}).get(name) != manifest["output_digest"]:
            return f"its {reader} read another {name} than the one on disk now (rerun since)"
    return None


def _read_run(method: str, seed: int, dirs: dict[str, Path]) -> MethodRun:
    manifests = {stage: _manifest(d) for stage, d in dirs.items()}
    label = manifests["evaluate"]["config"]["method"].get("label", method)
    table = read_table(dirs["evaluate"] / "metrics.parquet", METRICS)
    return MethodRun(
        method, seed, str(label), dirs["evaluate"], {k: np.asarray(v) for k, v in table.items()}, manifests
    )


def _comparison_rows(runs: list[MethodRun]) -> dict[str, list]:
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


def _seed_values(
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


def _lookup(rows: dict[str, list], method: str, split: str, region: str, group: str = "all") -> dict[str, float]:
    """metric -> the mean over ``method``'s seeds (NaN where it has no row)."""
    return {
        m: float(np.nanmean(v)) if v.size and np.isfinite(v).any() else float("nan")
        for m, v in _seed_values(rows, method, split, region, group).items()
    }


def _spread(values: np.ndarray) -> float:
    """Sample standard deviation (ddof 1) of the finite ``values``; NaN below two."""
    values = values[np.isfinite(values)]
    return float(np.std(values, ddof=1)) if values.size >= 2 else float("nan")


def _cost(runs: list[MethodRun], shared: dict[str, dict[str, Any]]) -> dict[str, float]:
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


def _fmt(value: float, digits: int) -> str:
    return "-" if not np.isfinite(value) else f"{value:.{digits}f}"


def _metric_cells(values: dict[str, float]) -> list[str]:
    return [_fmt(values["psnr"], 2), _fmt(values["ssim"], 4), _fmt(values["lpips"], 4)]


def _stat(values: np.ndarray, digits: int) -> str:
    """The seeds' mean, with ``± standard deviation`` when there are two or more: ``31.12 ± 0.08``."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return "-"
    mean = _fmt(float(finite.mean()), digits)
    return mean if finite.size < 2 else f"{mean} ± {_spread(finite):.{digits}f}"


def _stat_cells(rows: dict[str, list], method: str, split: str, region: str, group: str = "all") -> list[str]:
    values = _seed_values(rows, method, split, region, group)
    return [_stat(values["psnr"], 2), _stat(values["ssim"], 4), _stat(values["lpips"], 4)]


#: the regions (and frame group) of the seeds table: where the full model's effects act
SEED_REGIONS = (("full", "all"), ("hand", "all"), ("face", "all"), ("interaction", "all"), ("interaction", "contact"))
SIGNIFICANCE = 0.05


def _seed_table(rows: dict[str, list], present: dict[str, str], full: str, splits: list[str]) -> list[list[str]]:
    """Rows of the full model's PSNR minus each other method's (``present``: method -> label), per split and
    region: the difference of the means, the larger of the two seed spreads, Welch's p and what the seeds
    support."""
    out = []
    for split in splits:
        for method in present:
            if method == full:
                continue
            for region, group in SEED_REGIONS:
                a = _seed_values(rows, full, split, region, group)["psnr"]
                b = _seed_values(rows, method, split, region, group)["psnr"]
                if not (np.isfinite(a).any() and np.isfinite(b).any()):
                    continue
                diff = float(np.nanmean(a) - np.nanmean(b))
                spread = float(np.nanmax([_spread(a), _spread(b)])) if max(a.size, b.size) >= 2 else float("nan")
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
                        _fmt(spread, 2),
                        _fmt(p, 3),
                        verdict,
                    ]
                )
    return out


def _run_args(method: str, seed: int) -> str:
    """The command-line overrides that select one training run."""
    return f"method={method}" + (f" seed={seed}" if seed else "")


def _tables(
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
    paper_cells = lambda m, split: _metric_cells(paper) if (paper := present[m].paper(split)) else ["-"] * 3  # noqa: E731
    splits = [s for s in SPLITS if s in set(rows["split"])]
    in_table = {
        t: sorted(
            (m for m, r in present.items() if r.position(t) is not None), key=lambda m: (present[m].position(t), m)
        )
        for t in TABLES
    }
    full = min((m for m, r in present.items() if r.role.get("full_model")), default=None)
    table1 = [
        [split, present[m].label, *_stat_cells(rows, m, split, "full"), *paper_cells(m, split)]
        for split in splits
        for m in in_table["baselines"]
    ]
    table2 = [
        [
            split,
            present[m].label,
            *(_stat(_seed_values(rows, m, split, region)["psnr"], 2) for region in ("full", "hand", "interaction")),
            *(_stat(_seed_values(rows, m, split, region)["lpips"], 4) for region in ("full", "hand", "interaction")),
            _stat(_seed_values(rows, m, split, "interaction", "contact")["psnr"], 2),
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
                        "rows": _seed_table(rows, {m: r.label for m, r in present.items()}, full, splits),
                    }
                ]
                if full is not None and len(seeds) >= 2
                else []
            ),
        ],
        "notes": notes,
        "missing": missing,
    }


def _markdown(tables: dict[str, Any]) -> str:
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


def _figure(
    runs: list[MethodRun], frames_dir: Path, split: str, sequence: str, crop: str, px: int
) -> np.ndarray | None:
    """Rows of showcase frames, columns ground truth then each method that rendered ``split``, cropped to the
    hand box or the hand-face overlap box of the ground truth's labels; ``None`` when no frame has that box."""
    runs = [r for r in runs if (r.evaluate_dir / "renders" / split).is_dir()]
    if not runs:
        return None
    render_dir = runs[0].evaluate_dir / "renders" / split
    rows = []
    for path in sorted(render_dir.glob("*.png")):
        frame_text, camera_id = path.stem.split("_", 1)
        frame = int(frame_text)
        labels = read_png(crop_mask_path(frames_dir, sequence, camera_id, frame), 1)
        hand = label_box(labels, MASK_LABELS["hand"])
        box = hand if crop == "hand" else overlap_box(hand, label_box(labels, MASK_LABELS["face"]))
        if box is None:
            continue
        images = [read_png(rgb_path(frames_dir, sequence, camera_id, frame), 3)]
        images += [read_png(showcase_path(r.evaluate_dir, split, frame, camera_id), 3) for r in runs]
        rows.append(np.concatenate([_crop(image, box, px) for image in images], axis=1))
    if not rows:
        return None
    header = np.full((18, rows[0].shape[1], 3), 255, np.uint8)
    for i, name in enumerate(["ground truth"] + [r.label for r in runs]):
        cv2.putText(header, name[:16], (i * px + 2, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([header, *rows], axis=0)


def _crop(image: np.ndarray, box: np.ndarray, px: int) -> np.ndarray:
    """The square around ``box`` (x0, y0, x1, y1) of ``image`` (S, S, 3), resized to (px, px, 3)."""
    size = image.shape[0]
    x0, y0, x1, y1 = box
    side = max(x1 - x0, y1 - y0, 8.0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    lo_x = int(np.clip(round(cx - side / 2), 0, max(size - side, 0)))
    lo_y = int(np.clip(round(cy - side / 2), 0, max(size - side, 0)))
    side_px = int(min(round(side), size))
    patch = image[lo_y : lo_y + side_px, lo_x : lo_x + side_px]
    return cv2.resize(patch, (px, px), interpolation=cv2.INTER_AREA if side_px > px else cv2.INTER_NEAREST)
