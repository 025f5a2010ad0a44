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
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig

from data_schemas.images import write_png
from data_schemas.metrics import COMPARISON
from data_schemas.tables import write_table
from data_schemas.writes import write_bytes, write_json
from pipeline.config import fix_command, group_options
from pipeline.stage import StageContext, stage
from pipeline.workspace import method_run
from reporting.comparison_figure import image_row_figure
from reporting.comparison_tables import comparison_rows, comparison_tables, markdown, run_args, run_cost
from reporting.method_runs import SHARED_STAGES, read_run, split_sequences, stage_manifest, stale_reason


@dataclass
class CompareConfig:
    """Types of ``stage.compare`` (values in conf/stage/compare.yaml)."""

    methods: list[str]
    seeds: list[int]
    crop_px: int


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
        read_run(m, seed, {stage: dirs[stage][method_run(m, seed)] for stage in dirs})
        for m, seed in listed
        if all(method_run(m, seed) in dirs[stage] for stage in dirs)
    ]
    shared = {name: stage_manifest(ctx.input_dir(name)) for name in SHARED_STAGES}
    stale = {
        r.run: (why, run_args(r.name, r.seed)) for r in found if (why := stale_reason(r.manifests, shared)) is not None
    }
    runs = [r for r in found if r.run not in stale]
    corrupt = {
        method_run(m, seed): (ctx.method_problems[method_run(m, seed)], run_args(m, seed))
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
    rows = comparison_rows(runs)
    write_table(
        ctx.out_dir / "comparison.parquet",
        COMPARISON,
        {c.name: (rows[c.name] if c.kind == "string" else np.asarray(rows[c.name])) for c in COMPARISON.columns},
    )
    cost = run_cost(runs, shared)
    tables = comparison_tables(
        runs, rows, missing, cost, stale, corrupt
    )  # artifacts hold no run's command line: see comparison_tables
    write_json(ctx.out_dir / "tables.json", tables, "the comparison tables")
    write_bytes(ctx.out_dir / "tables.md", markdown(tables).encode(), "the comparison tables")
    (ctx.out_dir / "figures").mkdir()
    first_seed = [r for r in runs if r.seed == int(conf.seeds[0])]  # the image rows: one run per method
    for split, sequence in split_sequences(first_seed).items():
        for crop in ("hand", "interaction"):
            figure = image_row_figure(first_seed, ctx.input_dir("frames"), split, sequence, crop, int(conf.crop_px))
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
