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
and face: how much a better hand model could still gain); then the cost table: the warm-up step and the
stage-two step measured side by side from the same warm-up (interleaved rounds, medians), their RATIO, the
stage-two step split into PointNet++, MLPs, posing/glue, rasterizer, loss, backward and optimizer, and the load;
appended to ``benchmarks/results/bench_dynamic.json`` and ``.md`` (commit, preset, machine, load).

Nothing here is tuned on the held-out camera or motion: the stage's defaults were chosen on the training
views (see docs/explanation/dynamic-model.md).

Usage: python benchmarks/bench_dynamic.py [--subjects synth_a synth_b] [--presets draft] [--outputs DIR]
       [--set stage.dynamic.seed=1 ...] [--no-run] [--cost-only [--cost-steps 20 --cost-rounds 3]]

``--no-run`` trains nothing: it prints the quality tables and the error budget of the variants already in
``--outputs`` (e.g. of an earlier run, or one made with the CLI and ``method.name=static_same_steps``).
``--cost-only`` runs the DAG until the warm-up (cached in ``--outputs``) and prints only the cost table.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook  # noqa: E402

from avatar.artifacts import TRAIN_SEQUENCE, contact_flags, load_scene, load_views, method_params  # noqa: E402
from avatar.artifacts.motion import applied_deformation, posed_sequence, templates  # noqa: E402
from avatar.dynamic.conditioning import Conditioning  # noqa: E402
from avatar.geometry.views import ViewSet  # noqa: E402
from avatar.metrics.lpips import LPIPS  # noqa: E402
from avatar.posing import MeshSequence  # noqa: E402
from avatar.representations.bound.dynamic_model import DynamicAvatar, DynamicModelConfig  # noqa: E402
from avatar.representations.bound.gaussians import BoundGaussians  # noqa: E402
from avatar.representations.bound.representation import load_gaussians, model_config  # noqa: E402
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic  # noqa: E402
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from data_schemas.capture import MASK_LABELS  # noqa: E402
from data_schemas.frames import UNOBSERVED  # noqa: E402
from data_schemas.metrics import METRICS, REGIONS, SPLIT_SOURCES  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from stages import REGISTRY  # noqa: E402

#: variant -> (method name, overrides): the static variant is a method defined on the command line (the
#: full model's warm-up and PBD, H and I off, no patch loss), so it shares the full model's warm-up.
VARIANTS = {
    "full": ("interactavatar", ["method=interactavatar"]),
    "static": (
        "static_same_steps",
        [
            "method.name=static_same_steps",
            "stage.dynamic.hand_mlp=false",
            "stage.dynamic.interaction=false",
            "stage.dynamic.patch_weight=0",
        ],
    ),
}


def compose_cfg(preset: str, subject: str, outputs: Path, extra: list[str], until: str = "evaluate"):  # DictConfig
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"quality={preset}",
                f"subject={subject}",
                f"paths.outputs={outputs}",
                f"run.until={until}",
                "run.progress=false",
                "fit.source=ground_truth",
                *extra,
            ],
        )
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
    return {
        "wall_s": wall_s,
        "manifests": manifests,
        "metrics": read_table(root / "evaluate" / "metrics.parquet", METRICS),
    }


def _mean(t: dict, method: str, metric: str, split: str, region: str, contact: bool | None) -> float:
    """Mean of the finite ``metric`` values of ``method`` in ``split`` and ``region`` (contact frames, the others,
    or all for ``None``)."""
    sel = [
        i
        for i in range(len(t["frame"]))
        if t["method"][i] == method
        and t["split"][i] == split
        and t["region"][i] == region
        and (contact is None or bool(t["contact"][i]) == contact)
    ]
    v = np.asarray(t[metric], dtype=np.float64)[sel]
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def region_rows(full: dict, static: dict) -> list[tuple]:
    """One row per split x region x contact: both methods' means and the differences."""
    rows = []
    a, b = full["metrics"], static["metrics"]
    for split in ("novel_view", "self_reenact"):
        for region in REGIONS:
            for contact in (None, True, False):
                where = (split, region, contact)
                f = {m: _mean(a, VARIANTS["full"][0], m, *where) for m in ("psnr", "ssim", "lpips")}
                s = {m: _mean(b, VARIANTS["static"][0], m, *where) for m in ("psnr", "ssim", "lpips")}
                label = "all" if contact is None else ("contact" if contact else "no contact")
                rows.append(
                    (
                        split,
                        region,
                        label,
                        f"{s['psnr']:.2f}",
                        f"{f['psnr']:.2f}",
                        f"{f['psnr'] - s['psnr']:+.2f}",
                        f"{s['ssim']:.4f}",
                        f"{f['ssim']:.4f}",
                        f"{s['lpips']:.4f}",
                        f"{f['lpips']:.4f}",
                        f"{f['lpips'] - s['lpips']:+.4f}",
                    )
                )
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
        by_key = {
            (int(f), c, r): float(p)
            for s, f, c, r, p, m in zip(
                metrics["split"],
                metrics["frame"],
                metrics["camera_id"],
                metrics["region"],
                metrics["psnr"],
                metrics["method"],
            )
            if s == split and m == method
        }
        full, hand_oracle, both_oracle, shares = [], [], [], []
        for t in range(labels.num_frames):
            for c, camera_id in enumerate(labels.camera_ids):
                lab = labels.labels[t, c].numpy()
                count = {r: int((lab == MASK_LABELS[r]).sum()) for r in ("hand", "face")}
                sse = {
                    r: 10 ** (-by_key[(t, camera_id, r)] / 10) * count[r] if count[r] else 0.0 for r in ("hand", "face")
                }
                psnr_full = by_key[(t, camera_id, "full")]  # over the observed pixels (no crop padding)
                observed = int((lab != UNOBSERVED).sum())
                sse_full = 10 ** (-psnr_full / 10) * observed
                full.append(psnr_full)
                hand_oracle.append(-10 * np.log10((sse_full - sse["hand"]) / observed))
                both_oracle.append(-10 * np.log10((sse_full - sse["hand"] - sse["face"]) / observed))
                shares.append(
                    (
                        sse["hand"] / sse_full,
                        sse["face"] / sse_full,
                        1 - (sse["hand"] + sse["face"]) / sse_full,
                        count["hand"] / observed,
                    )
                )
        f, h, b, s = np.mean(full), np.mean(hand_oracle), np.mean(both_oracle), np.mean(shares, axis=0)
        rows.append(
            (
                split,
                variant,
                f"{f:.2f}",
                f"{h:.2f} ({h - f:+.2f})",
                f"{b:.2f} ({b - f:+.2f})",
                f"{s[0]:.0%} / {s[1]:.0%} / {s[2]:.0%}",
                f"{s[3]:.1%}",
            )
        )
    return rows


@contextmanager
def _forward_timers(modules: dict[str, torch.nn.Module | None], seconds: dict[str, float]) -> Iterator[None]:
    """Add each module's forward wall time to ``seconds[name]`` while inside (``None`` modules are skipped)."""
    started: dict[str, float] = {}
    handles = []
    for name, module in modules.items():
        if module is None:
            continue
        handles.append(
            module.register_forward_pre_hook(lambda *_a, n=name: started.__setitem__(n, time.perf_counter()))
        )
        handles.append(
            module.register_forward_hook(
                lambda *_a, n=name: seconds.__setitem__(n, seconds.get(n, 0.0) + time.perf_counter() - started[n])
            )
        )
    handles.append(register_optimizer_step_pre_hook(lambda *_a: started.__setitem__("optimizer", time.perf_counter())))
    handles.append(
        register_optimizer_step_post_hook(
            lambda *_a: seconds.__setitem__(
                "optimizer", seconds.get("optimizer", 0.0) + time.perf_counter() - started["optimizer"]
            )
        )
    )
    try:
        yield
    finally:
        for handle in handles:
            handle.remove()


@dataclasses.dataclass
class StageTwoInputs:
    """What a stage-two step reads, from a cached warm-up, on ``device``: the crops, the posed meshes, the
    conditioning and the contact flags of the train motion, the warm-up's Gaussians (on the CPU, as the stage loads
    them), the architecture and the patch loss's network."""

    device: str
    views: ViewSet
    meshes: MeshSequence
    cond: Conditioning
    contact: np.ndarray
    gaussians: BoundGaussians
    arch: DynamicModelConfig
    num_face_vertices: int
    frame_dims: dict[str, int]
    patch_weight: float
    lpips: LPIPS | None

    def model(self, seed: int, heads: str = "per_parameter", precision: str = "fp32") -> DynamicAvatar:
        """A fresh stage-two model from a copy of the warm-up Gaussians, built on the CPU and moved, as the stage
        builds it."""
        cpu = self.meshes.to("cpu")
        model = DynamicAvatar.from_warmup(
            copy.deepcopy(self.gaussians),
            cpu.vertices[0],
            cpu.faces,
            cpu.part_names,
            self.num_face_vertices,
            self.frame_dims,
            dataclasses.replace(self.arch, heads=heads),
            seed=seed,
        ).to(self.device)
        model.precision = precision
        return model


def stage_two_inputs(preset: str, subject: str, outputs: Path, extra: list[str], device: str = "cpu") -> StageTwoInputs:
    """The inputs of stage two at ``preset`` from the full model's cached warm-up in ``outputs``, on ``device``."""
    cfg = compose_cfg(preset, subject, outputs, VARIANTS["full"][1] + extra)
    root = outputs / subject
    warm = root / "methods" / VARIANTS["full"][0] / "warmup"
    views = load_views(root / "capture", root / "frames", "train", "train", device)
    posed = posed_sequence(
        root / "fit",
        TRAIN_SEQUENCE,
        cfg,
        applied_deformation(cfg, root / "pbd"),
        method_params(warm, root / "fit", TRAIN_SEQUENCE),
    )
    meshes, cond = posed.meshes, posed.conditioning(cfg)
    head, _ = templates(cfg.model)
    patch_weight = float(cfg.stage.dynamic.patch_weight)
    return StageTwoInputs(
        device,
        views,
        meshes.to(device),
        cond.to(device),
        contact_flags(root / "pbd", "train", views.num_frames),
        load_gaussians(warm, meshes.part_names),
        model_config(cfg, load_scene(root / "scene")),
        head.num_vertices,
        {"hand_pose": cond.hand_pose.shape[1], "expression": cond.expression.shape[1]},
        patch_weight,
        LPIPS("vgg").to(device) if patch_weight > 0 else None,
    )


def synchronize(device: str) -> None:
    """Wait for the device's queued work (a CUDA device; nothing to wait for on the CPU), before reading a clock."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def step_costs(
    preset: str,
    subject: str,
    outputs: Path,
    extra: list[str],
    steps: int = 20,
    rounds: int = 3,
    heads: tuple[str, ...] = ("per_parameter",),
    device: str = "cpu",
) -> dict[str, float]:
    """ms per training step of the warm-up and of stage two from the same cached warm-up, side by side.

    Each round trains a copy of the warm-up Gaussians ``steps`` warm-up steps (``train_warmup`` without density
    control) and then the full model, built from them as the stage builds it, ``steps`` stage-two steps
    (``train_dynamic``: frames drawn as in training, contact frames oversampled); the rounds alternate the two, and
    every figure is the median over the rounds (after one untimed round of two steps each). The stage-two step is
    split into the forward passes of PointNet++, the MLPs (H_geo, H_app, I) and the rest of the model (posing,
    sampling, the delta glue), the rasterizer, the loss, the backward pass and the optimizer step.

    With several ``heads`` (``stage.dynamic.heads`` variants, ``<heads>+bf16`` with the networks in bfloat16 as
    ``run.precision=bf16`` runs them) each round trains stage two once per variant, in turn, from the same warm-up; the
    plain keys are the first variant's, ``<variant>_<part>_ms`` (the step and its parts) and ``<variant>_ratio``
    every variant's.

    On a CUDA ``device`` the data and the models live there and each round waits for the device before its clock
    stops; the parts are then the times at which the host queued them (the device runs behind), and only the step is
    the device's.
    """
    inputs = stage_two_inputs(preset, subject, outputs, extra, device)
    views, meshes, cond, contact, gaussians = (
        inputs.views,
        inputs.meshes,
        inputs.cond,
        inputs.contact,
        inputs.gaussians,
    )
    lpips = inputs.lpips

    def warmup_round(n: int, seed: int) -> float:
        model = copy.deepcopy(gaussians).to(device)
        synchronize(device)
        t0 = time.perf_counter()
        train_warmup(model, views, meshes, WarmupTrainConfig(steps=n, densify_from=1.0, densify_until=0.0, seed=seed))
        synchronize(device)
        return 1000 * (time.perf_counter() - t0) / n

    def dynamic_round(n: int, seed: int, variant: str) -> dict[str, float]:
        kind, _, precision = variant.partition("+")
        model = inputs.model(seed, kind, precision or "fp32")
        seconds: dict[str, float] = {}
        train_cfg = DynamicTrainConfig(steps=n, patch_weight=inputs.patch_weight, seed=seed)
        modules = {
            "pointnet": model.pointnet,
            "hand_geo": model.hand_geo,
            "hand_app": model.hand_app,
            "interaction": model.interaction,
        }
        synchronize(device)
        t0 = time.perf_counter()
        with _forward_timers(modules, seconds):
            result = train_dynamic(model, views, meshes, cond, contact, train_cfg, lpips=lpips)
        synchronize(device)
        wall = time.perf_counter() - t0
        mlp = sum(seconds.get(k, 0.0) for k in ("hand_geo", "hand_app", "interaction"))
        parts = {
            "step": wall,
            "pointnet": seconds.get("pointnet", 0.0),
            "mlps": mlp,
            "posing_glue": result.seconds["model"] - mlp - seconds.get("pointnet", 0.0),
            "render": result.seconds["render"],
            "loss": result.seconds["loss"],
            "backward": result.seconds["backward"] - seconds.get("optimizer", 0.0),
            "optimizer": seconds.get("optimizer", 0.0),
        }
        return {k: 1000 * v / n for k, v in parts.items()} | {"interaction_steps": result.interaction_steps / n}

    warmup_round(2, 0)
    for kind in heads:
        dynamic_round(2, 0, kind)
    warm_ms: list[float] = []
    runs: dict[str, list[dict[str, float]]] = {kind: [] for kind in heads}
    for r in range(rounds):
        warm_ms.append(warmup_round(steps, r))
        for kind in heads:
            runs[kind].append(dynamic_round(steps, r, kind))
    out = {
        "gaussians": gaussians.num_gaussians,
        "hand_gaussians": int((gaussians.part == meshes.part_names.index("hand")).sum().item()),
        "steps": steps,
        "rounds": rounds,
        "warmup_ms": statistics.median(warm_ms),
    }

    def medians(kind: str, prefix: str) -> dict[str, float]:  # the step, its parts (ms) and the interaction share
        first = runs[kind][0]
        named = {k: f"{prefix}{k}" if k == "interaction_steps" else f"{prefix}{k}_ms" for k in first}
        values = {named[k]: statistics.median(d[k] for d in runs[kind]) for k in first}
        return values | {f"{prefix}ratio": values[f"{prefix}step_ms"] / out["warmup_ms"]}

    out |= medians(heads[0], "")
    if len(heads) > 1:
        for kind in heads:
            out |= medians(kind, f"{kind}_")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", nargs="+", default=["synth_a", "synth_b"])
    parser.add_argument("--presets", nargs="+", default=["draft"])
    parser.add_argument("--outputs", type=Path, default=None, help="keep artifacts here (default: a temp dir)")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="extra config overrides for both variants, e.g. stage.dynamic.seed=1 (noise)",
    )
    parser.add_argument(
        "--no-run", action="store_true", help="train nothing: the tables of the variants already in --outputs"
    )
    parser.add_argument(
        "--cost-only", action="store_true", help="run the DAG until the warm-up (cached) and print only the cost table"
    )
    parser.add_argument("--cost-steps", type=int, default=20, help="steps per round of the step costs")
    parser.add_argument("--cost-rounds", type=int, default=3, help="interleaved rounds of the step costs")
    parser.add_argument(
        "--results",
        type=Path,
        default=REPO / "benchmarks" / "results",
        help="append the step costs to bench_dynamic.json and bench_dynamic.md here",
    )
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
                load0 = os.getloadavg()
                full = static = costs = None
                if args.cost_only:
                    cfg = compose_cfg(preset, subject, outputs, VARIANTS["full"][1] + args.set, until="warmup")
                    Runner(cfg, REGISTRY, log=lambda _m: None).run()
                elif args.no_run:
                    full, static = load_variant(outputs, subject, "full"), load_variant(outputs, subject, "static")
                else:
                    full = run_variant(preset, subject, outputs, "full", keep, args.set)
                    static = run_variant(preset, subject, outputs, "static", keep, args.set)
                if not args.no_run:
                    costs = step_costs(preset, subject, outputs, args.set, args.cost_steps, args.cost_rounds)
                load = (load0, os.getloadavg())
                print(
                    f"\n## {subject} at {preset} {' '.join(args.set)} (load average {load[0][0]:.1f} -> "
                    f"{load[1][0]:.1f})\n"
                )
                if full is not None:
                    print_quality(full, static, outputs / subject)
                rows = cost_rows(full, static, costs)
                print(format_table(("cost", "value"), rows))
                if costs is not None:
                    write_costs(args.results, preset, subject, costs, load, rows)
                sys.stdout.flush()


def print_quality(full: dict, static: dict, subject_dir: Path) -> None:
    """The quality tables of the two variants and their error budget."""
    steps_w = full["manifests"]["warmup"]["metrics"]["steps"]
    steps_d = full["manifests"]["dynamic"]["metrics"]["steps"]
    print(
        f"warm-up {steps_w} steps, stage two {steps_d} steps; static = warm-up + {steps_d} static "
        f"steps (same total {steps_w + steps_d})\n"
    )
    print(
        format_table(
            (
                "split",
                "region",
                "frames",
                "PSNR static",
                "PSNR full",
                "dPSNR",
                "SSIM static",
                "SSIM full",
                "LPIPS static",
                "LPIPS full",
                "dLPIPS",
            ),
            region_rows(full, static),
        )
    )
    print()
    print(
        format_table(
            (
                "split",
                "variant",
                "full-image PSNR",
                "perfect hand",
                "perfect hand and face",
                "squared error: hand / face / background",
                "hand pixels",
            ),
            [
                row
                for variant, v in (("static", static), ("full", full))
                for row in error_budget(subject_dir, variant, v["metrics"])
            ],
        )
    )
    print()


def cost_rows(full: dict | None, static: dict | None, costs: dict | None) -> list[tuple]:
    """The cost table: the side-by-side step costs (``costs`` from :func:`step_costs`; None: not measured), then
    from the trained variants (None: not trained) ms per step of the warm-up and both stage twos as the stages
    timed them, evaluations of I, peak memory and the DAG wall times."""
    rows = []
    if costs is not None:
        rows += [
            (
                f"side by side ({costs['rounds']} rounds of {costs['steps']} steps, medians; {costs['gaussians']} "
                f"Gaussians, {costs['hand_gaussians']} on the hand): warm-up ms/step",
                f"{costs['warmup_ms']:.0f}",
            ),
            ("stage two ms/step", f"{costs['step_ms']:.0f}"),
            ("RATIO stage two / warm-up", f"{costs['ratio']:.2f}"),
            ("  PointNet++ forward ms", f"{costs['pointnet_ms']:.0f}"),
            ("  MLPs forward ms (H_geo, H_app, I)", f"{costs['mlps_ms']:.0f}"),
            ("  posing / glue forward ms (the rest of the model)", f"{costs['posing_glue_ms']:.0f}"),
            ("  rasterizer forward ms", f"{costs['render_ms']:.0f}"),
            ("  loss ms", f"{costs['loss_ms']:.0f}"),
            ("  backward ms (everything)", f"{costs['backward_ms']:.0f}"),
            ("  optimizer step ms", f"{costs['optimizer_ms']:.0f}"),
            ("  steps with I evaluated", f"{costs['interaction_steps']:.0%}"),
        ]
    if full is None or static is None:
        return rows
    steps_w = full["manifests"]["warmup"]["metrics"]["steps"]
    warm_ms = 1000 * full["manifests"]["warmup"]["timings"]["wall_s"] / steps_w
    dm, sm = full["manifests"]["dynamic"]["metrics"], static["manifests"]["dynamic"]["metrics"]
    rows += [
        ("DAG run: warm-up ms/step (stage wall / steps, incl. density control and validation)", f"{warm_ms:.0f}"),
        ("DAG run: stage two full ms/step", f"{dm['ms_per_step']:.0f}"),
        ("DAG run: stage two static ms/step", f"{sm['ms_per_step']:.0f}"),
        (
            "  full: model forward / render / loss / backward ms",
            " / ".join(f"{dm[k + '_ms_per_step']:.0f}" for k in ("model", "render", "loss", "backward")),
        ),
        ("interaction-MLP evaluations (Gaussians, all steps)", dm["interaction_mlp_evaluations"]),
        ("steps with I evaluated", dm["interaction_steps"]),
        ("peak MB (dynamic stage)", f"{full['manifests']['dynamic']['peak_memory_mb']:.0f}"),
    ]
    if full["wall_s"] is not None:
        rows.append(("DAG wall s: full / static rerun", f"{full['wall_s']:.0f} / {static['wall_s']:.0f}"))
    return rows


def write_costs(results: Path, preset: str, subject: str, costs: dict, load: tuple, rows: list[tuple]) -> None:
    """Append the step costs to ``results/bench_dynamic.json`` and the cost table to ``bench_dynamic.md``
    (commit, preset, machine, threads, load before and after)."""
    results.mkdir(parents=True, exist_ok=True)
    run = {
        "commit": commit(),
        "preset": preset,
        "subject": subject,
        "machine": cpu_name(),
        "threads": torch.get_num_threads(),
        "load_before": list(load[0]),
        "load_after": list(load[1]),
        "made": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "costs": costs,
    }
    path = results / "bench_dynamic.json"
    previous = json.loads(path.read_text()) if path.is_file() else {"runs": []}
    previous["runs"].append(run)
    path.write_text(json.dumps(previous, indent=1))
    md_path = results / "bench_dynamic.md"
    if not md_path.is_file():
        md_path.write_text(
            "# bench_dynamic: the stage-two step against the warm-up step (issue 33)\n\n"
            "Appended by `benchmarks/bench_dynamic.py`, one section per subject, preset and run.\n"
        )
    with md_path.open("a") as md:
        md.write(
            f"\n## {subject} at {preset}: commit {run['commit']}, {run['machine']}, {run['threads']} threads, "
            f"load {' '.join(f'{x:.2f}' for x in load[0])} -> {' '.join(f'{x:.2f}' for x in load[1])}, "
            f"{run['made']}\n\n```\n{format_table(('cost', 'value'), rows)}\n```\n"
        )


if __name__ == "__main__":
    main()
