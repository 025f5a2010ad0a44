"""Tracking refined with the avatar: how the warm-up's refine_params learning rates trade (chosen on training views).

Reads a workspace whose fit has run (for instance the MediaPipe workspace of ``bench_seeds.py --setting m1``) and
trains GaussianAvatars' warm-up (``quality=draft`` settings) once per arm: without refinement, and with
``stage.warmup.params_lr`` at multiples of GaussianAvatars' values (``--scales``), free or centred. One *training*
camera is withheld from every arm (``--hold``; never the held-out camera, which no arm reads), and each arm is
scored on what the training views allow:

* ``withheld frames``: the validation PSNR on the train frames the warm-up withholds (posed as fitted: they are
  never refined), the mean of the last three validations; the analogue of the held-out motion.
* ``withheld camera``: the PSNR of the refined training frames seen from the withheld training camera; the analogue
  of the held-out camera (novel view).
* with a synthetic capture, the train frames' 3D errors against the generator's parameters (information only).

``--cost`` measures instead what the refinement adds to a warm-up step (interleaved runs, medians) and what its
parts cost. Appends to ``benchmarks/results/bench_train_refine.json`` (commit, machine, load, rows).

    .venv/bin/python benchmarks/bench_train_refine.py --workspace outputs/synth_a --scales 0 3 10 30 --centred
    .venv/bin/python benchmarks/bench_train_refine.py --workspace outputs/synth_a --cost
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from avatar.artifacts import load_ground_truth_params, load_views  # noqa: E402
from avatar.artifacts.motion import posed_sequence, templates  # noqa: E402
from avatar.geometry.views import ViewSet  # noqa: E402
from avatar.posing import posed_keypoints  # noqa: E402
from avatar.representations.bound.gaussians import BoundGaussians  # noqa: E402
from avatar.representations.bound.warmup import WarmupTrainConfig, colors_from_views, render_frame, train_warmup  # noqa: E402
from avatar.training.frame_params import GAUSSIAN_AVATARS_RATES, FrameParams, ParamLearningRates  # noqa: E402
from avatar.training.validation import ValidationConfig, Validator  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from data_schemas.capture import MASK_LABELS, CaptureIndex  # noqa: E402
from pipeline.summary import format_table  # noqa: E402

DRAFT = WarmupTrainConfig(steps=2000, opacity_reset_interval=0.25, max_gaussians=100_000, seed=0)  # conf/quality/draft
GAUSSIANS_PER_TRIANGLE, INIT_OPACITY, VALIDATION = 2, 0.3, ValidationConfig(every=200, frames=4)
BASE = GAUSSIAN_AVATARS_RATES  # the defaults (ParamLearningRates(), conf/stage/warmup.yaml) are 10x these


def _cameras(views: ViewSet, index: list[int]) -> ViewSet:
    return ViewSet(
        views.images[:, index],
        views.labels[:, index],
        views.K[index],
        views.world_to_cam[index],
        [views.camera_ids[c] for c in index],
        views.background,
    )


def _psnr(gt: torch.Tensor, pred: torch.Tensor) -> float:
    return float(-10 * torch.log10(((gt - pred) ** 2).mean().clamp_min(1e-12)))


def arm(workspace: Path, scale: float, centred: bool, hold: str, steps: int) -> dict:
    """Train one warm-up and score it (see the module docstring)."""
    torch.manual_seed(0)
    cfg = OmegaConf.create({"model": {"flame_path": None, "mano_path": None}})
    head, hand = templates(cfg.model)
    views_all = load_views(workspace / "capture", workspace / "frames", "train", "train")
    hold_index = views_all.camera_ids.index(hold)
    views = _cameras(views_all, [c for c in range(views_all.num_cameras) if c != hold_index])
    withheld = _cameras(views_all, [hold_index])
    posed = posed_sequence(workspace / "fit", "train", cfg, None)  # GaussianAvatars: no contact offsets
    meshes = posed.meshes
    lrs = ParamLearningRates(*(scale * getattr(BASE, k) for k in ("rotation", "pose", "translation", "expression")))
    params = FrameParams(posed.params, head, hand, None, lrs, centred=centred) if scale > 0 else None
    model = BoundGaussians.on_triangles(
        meshes.vertices[0], meshes.faces, meshes.face_part, GAUSSIANS_PER_TRIANGLE, init_opacity=INIT_OPACITY, seed=0
    )
    with torch.no_grad():
        means, _, _ = model.world(meshes.vertices[0], meshes.faces)
    part_label = torch.tensor([MASK_LABELS[n] for n in meshes.part_names])[model.part]
    model.set_colors(colors_from_views(means, part_label, views, frame=0))
    validator = Validator(VALIDATION, views)
    start = time.perf_counter()
    train_warmup(model, views, meshes, dataclasses.replace(DRAFT, steps=steps), validator=validator, params=params)
    seconds = time.perf_counter() - start - validator.validation_s
    trained = validator.train_frames
    with torch.no_grad():
        camera_psnr = []
        for f in map(int, trained):
            out, _ = render_frame(
                model, meshes, withheld, f, 0, "auto", params.vertices(f) if params is not None else None
            )
            camera_psnr.append(_psnr(*withheld.target_and_render(out.rgb.clamp(0, 1), f, 0)))
    row = {
        "workspace": str(workspace),
        "scale": scale,
        "centred": centred,
        "withheld_camera": hold,
        "withheld_frames_psnr": float(np.mean([r.psnr for r in validator.curve[-3:]])),
        "withheld_camera_psnr": float(np.mean(camera_psnr)),
        "train_seconds": seconds,
        "steps": steps,
    }
    if CaptureIndex.read(workspace / "capture").sequences["train"].has_ground_truth:
        truth = posed_keypoints(load_ground_truth_params(workspace / "capture", "train"), head, hand)
        after = params.arrays() if params is not None else posed.params
        for name, p in (("fit", posed.params), ("refined", after)):
            pose = posed_keypoints(p, head, hand)
            for key in ("hand", "face", "hand_vertices", "face_vertices"):
                row[f"{name}_{key}_mm"] = float(
                    1e3 * np.linalg.norm(pose[key] - truth[key], axis=-1).mean(-1)[trained].mean()
                )
    return row


def cost(workspace: Path, steps: int, repeats: int) -> dict:
    """Milliseconds per warm-up step without and with the refinement (``repeats`` runs of ``steps`` steps each,
    interleaved; medians), and of the refinement's own parts on one frame: posing with its gradient and the
    row-wise Adam step (both stages), the conditioning from the refined parameters (stage two)."""
    cfg = OmegaConf.create({"model": {"flame_path": None, "mano_path": None}})
    head, hand = templates(cfg.model)
    views = load_views(workspace / "capture", workspace / "frames", "train", "train")
    posed = posed_sequence(workspace / "fit", "train", cfg, None)
    meshes, frames = posed.meshes, np.arange(views.num_frames)
    timings: dict[str, list[float]] = {"off": [], "on": []}
    warm = BoundGaussians.on_triangles(
        meshes.vertices[0], meshes.faces, meshes.face_part, GAUSSIANS_PER_TRIANGLE, init_opacity=INIT_OPACITY, seed=0
    )
    train_warmup(warm, views, meshes, dataclasses.replace(DRAFT, steps=10))  # caches and allocator, not timed
    for _ in range(repeats):
        for name in timings:
            params = (
                FrameParams(posed.params, head, hand, None, ParamLearningRates(), centred=True)
                if name == "on"
                else None
            )
            model = BoundGaussians.on_triangles(
                meshes.vertices[0],
                meshes.faces,
                meshes.face_part,
                GAUSSIANS_PER_TRIANGLE,
                init_opacity=INIT_OPACITY,
                seed=0,
            )
            start = time.perf_counter()
            train_warmup(model, views, meshes, dataclasses.replace(DRAFT, steps=steps), params=params)
            timings[name].append(1e3 * (time.perf_counter() - start) / steps)
    params = FrameParams(posed.params, head, hand, None, ParamLearningRates(), centred=True)
    parts: dict[str, list[float]] = {"posing_forward_backward_step": [], "conditioning": []}
    for t in range(4 * views.num_frames):
        frame = t % views.num_frames
        start = time.perf_counter()
        params.vertices(frame).square().sum().backward()
        params.step(frame, frames)
        middle = time.perf_counter()
        params.conditioning(frame)
        parts["posing_forward_backward_step"].append(1e3 * (middle - start))
        parts["conditioning"].append(1e3 * (time.perf_counter() - middle))
    out = {f"warmup_step_ms_{k}": float(np.median(v)) for k, v in timings.items()}
    out["warmup_step_ratio"] = out["warmup_step_ms_on"] / out["warmup_step_ms_off"]
    return out | {f"{k}_ms": float(np.median(v)) for k, v in parts.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True, help="a subject's folder under paths.outputs")
    parser.add_argument(
        "--scales",
        type=float,
        nargs="+",
        default=[0, 3, 10, 30],
        help="multiples of GaussianAvatars' learning rates (0: no refinement)",
    )
    parser.add_argument("--centred", action="store_true", help="also run each scale > 0 centred")
    parser.add_argument("--hold", default=None, help="the training camera withheld (default: the last)")
    parser.add_argument("--steps", type=int, default=DRAFT.steps)
    parser.add_argument("--cost", action="store_true", help="measure the cost instead of the arms")
    parser.add_argument("--repeats", type=int, default=3, help="--cost: interleaved runs per arm")
    parser.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    load_before = os.getloadavg()
    if args.cost:
        rows = [cost(args.workspace, min(args.steps, 200), args.repeats)]
        print(format_table(tuple(rows[0]), [[f"{v:.2f}" for v in rows[0].values()]]))
    else:
        train_ids = load_views(args.workspace / "capture", args.workspace / "frames", "train", "train").camera_ids
        hold = args.hold or train_ids[-1]
        arms = [(s, False) for s in args.scales] + [(s, True) for s in args.scales if args.centred and s > 0]
        rows = [arm(args.workspace, s, c, hold, args.steps) for s, c in arms]
        keys = (
            "scale",
            "centred",
            "withheld_frames_psnr",
            "withheld_camera_psnr",
            "refined_hand_mm",
            "refined_face_mm",
            "train_seconds",
        )
        print(
            format_table(
                keys,
                [
                    [f"{r.get(k, float('nan')):.2f}" if isinstance(r.get(k), float) else str(r.get(k)) for k in keys]
                    for r in rows
                ],
            )
        )
    args.results.mkdir(parents=True, exist_ok=True)
    out = args.results / "bench_train_refine.json"
    previous = json.loads(out.read_text()) if out.is_file() else {"runs": []}
    previous["runs"].append(
        {
            "commit": commit(),
            "machine": cpu_name(),
            "workspace": str(args.workspace),
            "load_before": load_before,
            "load_after": os.getloadavg(),
            "threads": torch.get_num_threads(),
            "kind": "cost" if args.cost else "arms",
            "rows": rows,
        }
    )
    out.write_text(json.dumps(previous, indent=1))
    print(out)


if __name__ == "__main__":
    main()
