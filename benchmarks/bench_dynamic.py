"""The dynamic model (stage two) against the static model given the same total number of steps.

For each subject and preset it runs the DAG until ``evaluate`` twice into one outputs folder (everything
upstream of ``dynamic`` is shared and cached):

1. ``full``: the InteractAvatar model, warm-up W steps then the hand MLPs H, the interaction MLPs I and
   PointNet++ for D steps;
2. ``static``: the same stage two with H and I switched off and no patch loss, i.e. the warm-up-only
   (GaussianAvatars) model trained W + D steps from the same warm-up;

and prints PSNR / SSIM / LPIPS of both on the held-out camera (novel view) and the held-out motion
(self-reenactment), on the full image and the hand, face and interaction regions, contact and non-contact
frames apart, with the differences; the error budget (how each variant's full-image squared error splits into
hand, face and background pixels, and the full-image PSNR of an oracle that is perfect on the hand, or on hand
and face: how much a better hand model could still gain); then the cost: ms per step of stage two against the
warm-up's, and a split of one stage-two step into PointNet++, MLPs and rendering (forward + backward, medians).

Nothing here is tuned on the held-out camera or motion: the stage's defaults were chosen on the training
views (see README).

Usage: python benchmarks/bench_dynamic.py [--subjects synth_a synth_b] [--presets draft] [--outputs DIR]
       [--set stage.dynamic.seed=1 ...] [--no-run]

``--no-run`` trains nothing: it prints the quality tables and the error budget of the variants already in
``--outputs`` (e.g. of an earlier run, or one made with the CLI and ``method.name=static_same_steps``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from avatar.gaussians.frames import place_gaussians, triangle_frames  # noqa: E402
from avatar.render.gaussians import render_gaussians  # noqa: E402
from avatar.training.dynamic import rasterize  # noqa: E402
from data_schemas.capture import MASK_LABELS  # noqa: E402
from data_schemas.deform import DEFORM  # noqa: E402
from data_schemas.frames import UNOBSERVED  # noqa: E402
from data_schemas.metrics import METRICS, REGIONS, SPLIT_SOURCES  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from stages import REGISTRY  # noqa: E402
from stages.common import load_dynamic, load_sequence, load_views  # noqa: E402

#: variant -> (method name, overrides): the static variant is a method defined on the command line (the
#: full model's warm-up and PBD, H and I off, no patch loss), so it shares the full model's warm-up.
VARIANTS = {
    "full": ("interactavatar", ["method=interactavatar"]),
    "static": ("static_same_steps", ["method.name=static_same_steps", "stage.dynamic.hand_mlp=false",
                                     "stage.dynamic.interaction=false", "stage.dynamic.patch_weight=0"]),
}


def compose_cfg(preset: str, subject: str, outputs: Path, extra: list[str]):  # noqa: ANN201 - DictConfig
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[f"quality={preset}", f"subject={subject}", f"paths.outputs={outputs}",
                                           "run.until=evaluate", "run.progress=false", "fit.source=ground_truth",
                                           *extra])
    return validate_config(cfg, REGISTRY)


def run_variant(preset: str, subject: str, outputs: Path, variant: str, keep: Path, extra: list[str]) -> dict:
    """Run the DAG for one variant; copy its evaluate metrics and grids to ``keep``; return ``load_variant``'s."""
    method, overrides = VARIANTS[variant]
    cfg = compose_cfg(preset, subject, outputs, overrides + extra)
    t0 = time.perf_counter()
    Runner(cfg, REGISTRY, log=lambda _m: None).run()
    wall = time.perf_counter() - t0
    root = outputs / subject / "methods" / method
    keep.mkdir(parents=True, exist_ok=True)
    shutil.copy(root / "evaluate" / "metrics.parquet", keep / f"metrics_{variant}.parquet")
    shutil.copytree(root / "evaluate" / "grids", keep / f"grids_{variant}", dirs_exist_ok=True)
    return load_variant(outputs, subject, variant, wall)


def load_variant(outputs: Path, subject: str, variant: str, wall_s: float | None = None) -> dict:
    """A variant's stage manifests and evaluate metrics from ``outputs``; ``wall_s``: its DAG run, if timed."""
    root = outputs / subject / "methods" / VARIANTS[variant][0]
    manifests = {s: json.loads((root / s / "_manifest.json").read_text()) for s in ("warmup", "dynamic", "evaluate")}
    return {"wall_s": wall_s, "manifests": manifests,
            "metrics": read_table(root / "evaluate" / "metrics.parquet", METRICS)}


def region_rows(full: dict, static: dict) -> list[tuple]:
    """One row per split x region x contact: both methods' means and the differences."""
    rows = []
    a, b = full["metrics"], static["metrics"]
    for split in ("novel_view", "self_reenact"):
        for region in REGIONS:
            for contact in (None, True, False):
                def mean(t: dict, method: str, metric: str) -> float:
                    sel = [i for i in range(len(t["frame"])) if t["method"][i] == method and t["split"][i] == split
                           and t["region"][i] == region and (contact is None or bool(t["contact"][i]) == contact)]
                    v = np.asarray(t[metric], dtype=np.float64)[sel]
                    v = v[np.isfinite(v)]
                    return float(v.mean()) if v.size else float("nan")
                f = {m: mean(a, VARIANTS["full"][0], m) for m in ("psnr", "ssim", "lpips")}
                s = {m: mean(b, VARIANTS["static"][0], m) for m in ("psnr", "ssim", "lpips")}
                label = "all" if contact is None else ("contact" if contact else "no contact")
                rows.append((split, region, label, f"{s['psnr']:.2f}", f"{f['psnr']:.2f}",
                             f"{f['psnr'] - s['psnr']:+.2f}", f"{s['ssim']:.4f}", f"{f['ssim']:.4f}",
                             f"{s['lpips']:.4f}", f"{f['lpips']:.4f}", f"{f['lpips'] - s['lpips']:+.4f}"))
    return rows


def error_budget(root: Path, variant: str, metrics: dict) -> list[tuple]:
    """Per split, where the variant's full-image squared error lives and what an oracle would gain.

    From the per-image region PSNRs of ``metrics`` (the evaluate table) and the crops' labels: the squared
    error summed over a region is ``10^(-PSNR / 10)`` times its pixel count (``avatar.metrics.psnr``), the
    hand and face labels are disjoint and the rest of the crop is background. "Perfect hand" is the
    full-image PSNR with the hand pixels' error removed (mean over images, like the table above).
    """
    method = VARIANTS[variant][0]
    rows = []
    for split, (sequence, cameras) in SPLIT_SOURCES.items():
        labels = load_views(root / "capture", root / "frames", sequence, cameras)
        by_key = {(int(f), c, r): float(p) for s, f, c, r, p, m in zip(
            metrics["split"], metrics["frame"], metrics["camera_id"], metrics["region"], metrics["psnr"],
            metrics["method"]) if s == split and m == method}
        full, hand_oracle, both_oracle, shares = [], [], [], []
        for t in range(labels.num_frames):
            for c, camera_id in enumerate(labels.camera_ids):
                lab = labels.labels[t, c].numpy()
                count = {r: int((lab == MASK_LABELS[r]).sum()) for r in ("hand", "face")}
                sse = {r: 10 ** (-by_key[(t, camera_id, r)] / 10) * count[r] if count[r] else 0.0
                       for r in ("hand", "face")}
                psnr_full = by_key[(t, camera_id, "full")]  # over the observed pixels (no crop padding)
                observed = int((lab != UNOBSERVED).sum())
                sse_full = 10 ** (-psnr_full / 10) * observed
                full.append(psnr_full)
                hand_oracle.append(-10 * np.log10((sse_full - sse["hand"]) / observed))
                both_oracle.append(-10 * np.log10((sse_full - sse["hand"] - sse["face"]) / observed))
                shares.append((sse["hand"] / sse_full, sse["face"] / sse_full,
                               1 - (sse["hand"] + sse["face"]) / sse_full, count["hand"] / observed))
        f, h, b, s = np.mean(full), np.mean(hand_oracle), np.mean(both_oracle), np.mean(shares, axis=0)
        rows.append((split, variant, f"{f:.2f}", f"{h:.2f} ({h - f:+.2f})", f"{b:.2f} ({b - f:+.2f})",
                     f"{s[0]:.0%} / {s[1]:.0%} / {s[2]:.0%}", f"{s[3]:.1%}"))
    return rows


def _median_ms(fn, repeats: int = 5) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def step_split(preset: str, subject: str, outputs: Path, extra: list[str]) -> dict[str, float]:
    """Forward + backward ms of PointNet++, the MLPs (H and I) and rendering on a contact frame of the trained
    full model, median of 5 each (the same camera and frame for all)."""
    cfg = compose_cfg(preset, subject, outputs, VARIANTS["full"][1] + extra)
    root = outputs / subject
    model = load_dynamic(root / "methods" / VARIANTS["full"][0] / "dynamic")
    views = load_views(root / "capture", root / "frames", "train", "train")
    meshes, cond = load_sequence(root / "fit", "train", cfg, pbd_dir=root / "pbd")
    deform = read_table(root / "pbd" / "train" / "deform.parquet", DEFORM)
    frame = int(np.flatnonzero(deform["contact"])[0]) if np.any(deform["contact"]) else 0
    c = cond.frame(frame)
    verts = meshes.vertices[frame]

    def whole() -> None:
        g = model(c, verts)
        rasterize(g, views, 0).rgb.sum().backward()
        model.zero_grad(set_to_none=True)

    def pointnet() -> None:
        with torch.no_grad():
            g = model.gaussians
            m, s, _ = place_gaussians(triangle_frames(verts, model.faces), g.binding, g.local_means,
                                      torch.exp(g.log_scales), g.quats)
            pts = model.geometry_points(c, m, s, torch.sigmoid(g.opacity_logits), None)
        model.geometry_feature(pts).sum().backward()
        model.zero_grad(set_to_none=True)

    def no_nets() -> None:
        g = model.gaussians
        means, scales, quats = g.world(verts, model.faces)
        render_gaussians(means, quats, scales, g.opacities(), g.colors(), views.K[0], views.world_to_cam[0],
                         views.size, views.size, views.background).rgb.sum().backward()
        model.zero_grad(set_to_none=True)

    whole_ms, pointnet_ms, render_ms = _median_ms(whole), _median_ms(pointnet), _median_ms(no_nets)
    return {"frame": frame, "whole_ms": whole_ms, "pointnet_ms": pointnet_ms, "render_ms": render_ms,
            "mlp_ms": whole_ms - pointnet_ms - render_ms}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", nargs="+", default=["synth_a", "synth_b"])
    parser.add_argument("--presets", nargs="+", default=["draft"])
    parser.add_argument("--outputs", type=Path, default=None, help="keep artifacts here (default: a temp dir)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="extra config overrides for both variants, e.g. stage.dynamic.seed=1 (noise)")
    parser.add_argument("--no-run", action="store_true",
                        help="train nothing: the tables of the variants already in --outputs")
    args = parser.parse_args()
    if args.no_run and args.outputs is None:
        parser.error("--no-run reads the variants of an earlier run: give its --outputs")
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    with tempfile.TemporaryDirectory() as tmp:
        base = args.outputs or Path(tmp)
        for preset in args.presets:
            for subject in args.subjects:
                outputs = base / preset
                keep = base / "results" / preset / subject
                load0 = os.getloadavg()[0]
                if args.no_run:
                    full, static, split = (load_variant(outputs, subject, "full"), load_variant(outputs, subject, "static"),
                                           None)
                else:
                    full = run_variant(preset, subject, outputs, "full", keep, args.set)
                    split = step_split(preset, subject, outputs, args.set)
                    static = run_variant(preset, subject, outputs, "static", keep, args.set)
                print(f"\n## {subject} at {preset} {' '.join(args.set)} (load average {load0:.1f} -> {os.getloadavg()[0]:.1f})\n")
                steps_w = full["manifests"]["warmup"]["metrics"]["steps"]
                steps_d = full["manifests"]["dynamic"]["metrics"]["steps"]
                print(f"warm-up {steps_w} steps, stage two {steps_d} steps; static = warm-up + {steps_d} static "
                      f"steps (same total {steps_w + steps_d})\n")
                print(format_table(("split", "region", "frames", "PSNR static", "PSNR full", "dPSNR", "SSIM static",
                                    "SSIM full", "LPIPS static", "LPIPS full", "dLPIPS"), region_rows(full, static)))
                print()
                print(format_table(("split", "variant", "full-image PSNR", "perfect hand", "perfect hand and face",
                                    "squared error: hand / face / background", "hand pixels"),
                                   [row for variant, v in (("static", static), ("full", full))
                                    for row in error_budget(outputs / subject, variant, v["metrics"])]))
                print()
                print(format_table(("cost", "value"), cost_rows(full, static, split)))
                sys.stdout.flush()


def cost_rows(full: dict, static: dict, split: dict | None) -> list[tuple]:
    """The cost table: ms per step of the warm-up and both stage twos, the full model's step split (``split``,
    from ``step_split``; None: not measured), evaluations of I, peak memory and the DAG wall times."""
    steps_w = full["manifests"]["warmup"]["metrics"]["steps"]
    warm_ms = 1000 * full["manifests"]["warmup"]["timings"]["wall_s"] / steps_w
    dm, sm = full["manifests"]["dynamic"]["metrics"], static["manifests"]["dynamic"]["metrics"]
    rows = [
        ("warm-up ms/step (stage wall / steps, incl. density control)", f"{warm_ms:.0f}"),
        ("stage two full ms/step", f"{dm['ms_per_step']:.0f}"),
        ("stage two static ms/step", f"{sm['ms_per_step']:.0f}"),
        ("  full: model forward / render / loss / backward ms",
         " / ".join(f"{dm[k + '_ms_per_step']:.0f}" for k in ("model", "render", "loss", "backward"))),
    ]
    if split is not None:
        rows += [
            (f"one step on contact frame {split['frame']}, fwd+bwd: PointNet++ ms", f"{split['pointnet_ms']:.0f}"),
            ("  MLPs ms (whole - PointNet++ - render)", f"{split['mlp_ms']:.0f}"),
            ("  render ms", f"{split['render_ms']:.0f}"),
        ]
    rows += [
        ("interaction-MLP evaluations (Gaussians, all steps)", dm["interaction_mlp_evaluations"]),
        ("steps with I evaluated", dm["interaction_steps"]),
        ("peak MB (dynamic stage)", f"{full['manifests']['dynamic']['peak_memory_mb']:.0f}"),
    ]
    if full["wall_s"] is not None:
        rows.append(("DAG wall s: full / static rerun", f"{full['wall_s']:.0f} / {static['wall_s']:.0f}"))
    return rows


if __name__ == "__main__":
    main()
