"""Quality against time and memory, per preset and method (issue 15): the speed/accuracy trade.

For each preset and method it runs the DAG until ``evaluate`` (into a temporary directory or ``--outputs``;
presets live in their own folders, methods share every stage upstream of the warm-up, as in ``make
compare``) and prints two tables:

- cost: wall time per stage (the shared ones computed once per preset, and counted in every method's row:
  each row is what one method's run costs from scratch), peak memory, Gaussians, and the run's total against
  the largest preset's for the same method;
- quality: PSNR / SSIM / LPIPS per split (NV: held-out camera; SR: held-out motion) and region (full,
  hand, interaction: the hand-face overlap box), mean over images; and NV PSNR as a share of the largest
  preset's.

With ``--early-stop`` every run is made twice with ``stage.warmup/dynamic.validation`` on (``--every``
steps; the same withheld training frames both times): planned schedule and ``stop_when_flat``, and a third
table gives the steps run, the training time saved and the held-out PSNR lost.

Goals (issue 15): ``draft`` reaches at least 95 % of ``standard``'s NV PSNR at no more than 20 % of its wall
time; the early stop saves at least 30 % of ``standard``'s training time for at most 0.2 dB.

Usage: python benchmarks/bench_quality.py [--presets smoke draft standard] [--methods gaussian_avatars
       interactavatar] [--outputs DIR] [--fit-source S] [--early-stop --every 100] [--results DIR]

The tables are appended to ``benchmarks/results/bench_quality.json`` (``--results``) with the commit, the
presets and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from data_schemas.metrics import METRICS  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from stages import REGISTRY  # noqa: E402

SHARED = ("capture", "frames", "keypoints", "fit", "scene", "pbd")
PER_METHOD = ("warmup", "dynamic", "evaluate")
SPLITS = {"novel_view": "NV", "self_reenact": "SR"}
REGIONS = ("full", "hand", "interaction")
NV_FULL = ("novel_view", "full", "psnr")


def run(preset: str, method: str, outputs: Path, fit_source: str, extra: list[str]) -> dict:
    """One DAG run until evaluate; the manifests of its stages and the evaluate metrics table."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"quality={preset}",
                f"paths.outputs={outputs}",
                "run.until=evaluate",
                "run.progress=false",
                f"fit.source={fit_source}",
                f"method={method}",
                *extra,
            ],
        )
    Runner(validate_config(cfg, REGISTRY), REGISTRY, log=lambda _m: None).run()
    root = outputs / cfg.subject
    folders = {s: root / s for s in SHARED} | {s: root / "methods" / method / s for s in PER_METHOD}
    return {
        "manifests": {s: json.loads((f / "_manifest.json").read_text()) for s, f in folders.items()},
        "metrics": read_table(folders["evaluate"] / "metrics.parquet", METRICS),
    }


def region_means(metrics: dict) -> dict[tuple[str, str, str], float]:
    """(split, region, metric) -> mean over the images where the region is present."""
    out = {}
    split, region = np.asarray(metrics["split"]), np.asarray(metrics["region"])
    for s in SPLITS:
        for r in REGIONS:
            rows = (split == s) & (region == r)
            for m in ("psnr", "ssim", "lpips"):
                values = np.asarray(metrics[m], float)[rows]
                out[(s, r, m)] = float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")
    return out


def wall(result: dict, stages: tuple[str, ...]) -> float:
    return sum(result["manifests"][s]["timings"]["wall_s"] for s in stages)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["smoke", "draft"])
    parser.add_argument("--methods", nargs="+", default=["gaussian_avatars", "interactavatar"])
    parser.add_argument("--outputs", type=Path, default=None, help="keep artifacts here (default: a temp dir)")
    parser.add_argument(
        "--fit-source",
        default="ground_truth",
        help="fit.source: ground_truth (default) measures the avatar apart from fitting error",
    )
    parser.add_argument("--early-stop", action="store_true", help="also measure stop_when_flat (two runs each)")
    parser.add_argument("--every", type=int, default=100, help="validation interval (steps) with --early-stop")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_quality", preset=",".join(args.presets))
    results: dict[tuple[str, str, str], dict] = {}
    validate = [f"stage.{s}.validation.every={args.every}" for s in ("warmup", "dynamic")]
    stop = [f"stage.{s}.validation.stop_when_flat.enabled=true" for s in ("warmup", "dynamic")]
    variants = {"plain": []} | ({"planned": validate, "stopped": validate + stop} if args.early_stop else {})
    with tempfile.TemporaryDirectory() as tmp:
        base = args.outputs or Path(tmp)
        for preset in args.presets:
            for variant, extra in variants.items():
                for method in args.methods:
                    results[(preset, method, variant)] = run(
                        preset, method, base / variant / preset, args.fit_source, extra
                    )
    largest = args.presets[-1]
    cost, quality = [], []
    for preset in args.presets:
        for method in args.methods:
            r = results[(preset, method, "plain")]
            ref = results[(largest, method, "plain")]
            # each row is one method's run from scratch: the shared stages (computed once per preset, by the
            # first method; every method reads the same manifests) plus its own
            shared = wall(r, SHARED)
            total = shared + wall(r, PER_METHOD)
            ref_total = wall(ref, SHARED) + wall(ref, PER_METHOD)
            peak = max(m["peak_memory_mb"] for m in r["manifests"].values())
            cost.append(
                (
                    preset,
                    method,
                    f"{shared:.0f}",
                    *(f"{r['manifests'][s]['timings']['wall_s']:.0f}" for s in PER_METHOD),
                    f"{total:.0f}",
                    f"{total / ref_total:.2f}",
                    f"{peak:.0f}",
                    r["manifests"]["dynamic"]["metrics"]["gaussians"],
                )
            )
            means, ref_means = region_means(r["metrics"]), region_means(ref["metrics"])
            quality.append(
                (
                    preset,
                    method,
                    *(
                        f"{means[(s, reg, m)]:.{2 if m == 'psnr' else 4}f}"
                        for s in SPLITS
                        for reg in REGIONS
                        for m in ("psnr", "ssim", "lpips")
                    ),
                    f"{100 * means[NV_FULL] / ref_means[NV_FULL]:.1f}",
                )
            )
    load = os.getloadavg()
    print(
        f"fit.source={args.fit_source}; load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}; ratios "
        f"against {largest}"
    )
    print(
        log.table(
            f"cost (fit.source={args.fit_source}; ratios against {largest})",
            (
                "preset",
                "method",
                "shared s",
                *(f"{s} s" for s in PER_METHOD),
                "total s",
                f"x {largest}",
                "peak MB",
                "Gaussians",
            ),
            cost,
        )
    )
    print()
    print(
        log.table(
            f"quality (fit.source={args.fit_source}; NV: held-out camera, SR: held-out motion)",
            (
                "preset",
                "method",
                *(f"{SPLITS[s]} {reg} {m}" for s in SPLITS for reg in REGIONS for m in ("PSNR", "SSIM", "LPIPS")),
                f"NV PSNR % {largest}",
            ),
            quality,
        )
    )
    if args.early_stop:
        rows = []
        for preset in args.presets:
            for method in args.methods:
                planned, stopped = results[(preset, method, "planned")], results[(preset, method, "stopped")]
                p_steps = sum(planned["manifests"][s]["metrics"]["steps"] for s in ("warmup", "dynamic"))
                s_steps = sum(stopped["manifests"][s]["metrics"]["steps"] for s in ("warmup", "dynamic"))
                p_s, s_s = wall(planned, ("warmup", "dynamic")), wall(stopped, ("warmup", "dynamic"))
                p_q, s_q = region_means(planned["metrics"]), region_means(stopped["metrics"])
                rows.append(
                    (
                        preset,
                        method,
                        p_steps,
                        s_steps,
                        f"{p_s:.0f}",
                        f"{s_s:.0f}",
                        f"{100 * (1 - s_s / p_s):.0f}",
                        *(f"{s_q[(s, 'full', 'psnr')] - p_q[(s, 'full', 'psnr')]:+.2f}" for s in SPLITS),
                    )
                )
        print()
        print(
            log.table(
                "early stop (stop_when_flat) against the planned schedule",
                (
                    "preset",
                    "method",
                    "planned steps",
                    "steps run",
                    "planned train s",
                    "stopped train s",
                    "time saved %",
                    "NV PSNR change",
                    "SR PSNR change",
                ),
                rows,
            )
        )
    log.write(args.results)


if __name__ == "__main__":
    main()
