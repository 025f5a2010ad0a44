"""The held-out motion tracked by the avatar: its settings chosen on the training views, and what it is worth.

``stage.evaluate.test_tracking=avatar`` (issue 54) against ground-truth tracking.

``rates``: chooses ``stage.evaluate.tracking`` without the held-out motion or the held-out camera. On a trained
workspace it tracks frames of the **train motion** with the method's final model frozen, starting from the fit's
parameters (not the ones training refined: the analogue of the held-out motion, which is posed as the fit left it),
on the tuning training cameras, and scores the other training cameras: full-image PSNR before and after, per setting
(steps, a multiple of every default rate), with the time per frame and the 3D errors against the synthetic truth
(information only). One setting after the other, one thread.

``cross``: the diagnosis. A ground-truth-trained avatar tracks the held-out motion from a fitted workspace's fit (its
poses with its shapes, then with the truth's shapes): how much of the gap the tracking closes when the avatar is not to
blame, and what is left to the identity.

``table``: reads evaluate's manifests of workspaces trained by ``benchmarks/bench_seeds.py`` (an arm each, e.g.
ground-truth tracking and MediaPipe tracking) and evaluated with ``stage.evaluate.test_tracking=avatar``, and prints per
subject, method and arm (mean ± sd over the seeds found): the held-out camera (NV), the held-out motion posed as the
fit tracked it on every training camera (SR tracker) and on the scoring cameras alone (SR tracker, scoring), and as
the avatar tracked it (SR avatar), full image; the fitted arm against the ground-truth arm; the held-out motion's 3D
errors before and after the avatar's tracking. Each writes a run to ``benchmarks/results/bench_test_tracking.json``.

Usage:
    python benchmarks/bench_test_tracking.py rates --workspace OUT/m2/synth_a --method interactavatar [--frames 6]
    python benchmarks/bench_test_tracking.py cross --trained OUT/a/synth_a --fitted OUT/m2/synth_a [--method M]
    python benchmarks/bench_test_tracking.py table --arm "ground truth=OUT/a" --arm "MediaPipe=OUT/m2" \\
        --subject synth_a [--reference "ground truth"]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from avatar.artifacts import (  # noqa: E402
    TRAIN_SEQUENCE,
    load_face_offsets,
    load_ground_truth_params,
    load_params,
    load_views,
)
from avatar.artifacts.motion import posed_with_offsets  # noqa: E402
from avatar.fitting.errors import tracking_errors  # noqa: E402
from avatar.geometry.views import ViewSet  # noqa: E402
from avatar.metrics.psnr import psnr  # noqa: E402
from avatar.representations import TrainedAvatar, load_trained  # noqa: E402
from avatar.templates import procedural_hand, procedural_head  # noqa: E402
from avatar.training.avatar_tracking import AvatarTrackingConfig, track_with_avatar, tracking_cameras  # noqa: E402
from avatar.training.rendering import rasterize  # noqa: E402
from benchmarks.bench_seeds import QUALITY_FILE  # noqa: E402
from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.workspace import method_run  # noqa: E402

METHODS = ("interactavatar", "gaussian_avatars")
#: (steps, rate multiple of the defaults) of the default sweep
SWEEP = ((40, 1.0), (20, 1.0), (80, 1.0), (40, 0.5), (40, 2.0))
#: what posing reads of a run's config: the procedural templates (the synthetic captures')
_CFG = OmegaConf.create({"model": {"flame_path": None, "mano_path": None, "face_stiffness_path": None}})


def _scaled(steps: int, multiple: float) -> AvatarTrackingConfig:
    base = AvatarTrackingConfig()
    rates = {f.name: getattr(base, f.name) * multiple for f in dataclasses.fields(base) if f.name.startswith("lr_")}
    return dataclasses.replace(base, steps=steps, **rates)


def _preset(subject_dir: Path) -> str:
    """The preset a bench_seeds setting's runs used (its ``quality.txt``), or ``unknown`` for another workspace."""
    path = subject_dir.parent / QUALITY_FILE
    return path.read_text().strip() if path.is_file() else "unknown"


def _scoring_psnr(model: TrainedAvatar, params: dict[str, np.ndarray], offsets: np.ndarray, views: ViewSet) -> float:
    """Mean full-image PSNR (dB, the observed pixels) of the frames posed with ``params`` over every camera of
    ``views``."""
    posed = posed_with_offsets(params, _CFG, offsets)
    cond = posed.conditioning(_CFG)
    values = []
    with torch.no_grad():
        for t in range(views.num_frames):
            gaussians = model.pose(cond, posed.meshes.vertices[t], t)
            for c in range(views.num_cameras):
                gt, pred = views.target_and_render(rasterize(gaussians, views, c).rgb.clamp(0, 1), t, c)
                observed = views.observed(t, c)  # as evaluate's full region: the pixels the camera saw
                values.append(float(psnr(pred.permute(2, 0, 1), gt.permute(2, 0, 1), observed)))
    return float(np.mean(values))


def rates(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    root = args.workspace.resolve()
    head, hand = procedural_head(), procedural_hand()
    dynamic = root / "methods" / method_run(args.method, args.seed) / "dynamic"
    model = load_trained(dynamic)
    uses_pbd = bool(json.loads((dynamic / "_manifest.json").read_text())["config"]["method.pbd"])
    views = load_views(root / "capture", root / "frames", TRAIN_SEQUENCE, "train")
    frames = np.unique(np.linspace(0, views.num_frames - 1, args.frames).round().astype(int))
    fitted = {k: v[frames] for k, v in load_params(root / "fit", TRAIN_SEQUENCE).items()}
    truth = {k: v[frames] for k, v in load_ground_truth_params(root / "capture", TRAIN_SEQUENCE).items()}
    offsets = (
        load_face_offsets(root / "pbd", TRAIN_SEQUENCE, views.num_frames, head.num_vertices)[frames]
        if uses_pbd
        else np.zeros((len(frames), head.num_vertices, 3))
    )
    subset = dataclasses.replace(views, images=views.images[frames], labels=views.labels[frames])
    tuning, scoring = tracking_cameras("auto", views.camera_ids)
    before = _scoring_psnr(model, fitted, offsets, subset.cameras(scoring))
    errors0 = tracking_errors(fitted, truth, head, hand)
    rows = [["fit", "-", "-", f"{before:.2f}", "-", "-", *(f"{errors0[k]:.2f}" for k in ERROR_KEYS)]]
    sweep = [(int(a), float(b)) for a, b in (item.split("x") for item in args.sweep)] if args.sweep else SWEEP
    for steps, multiple in sweep:
        started = time.perf_counter()
        tracked = track_with_avatar(
            lambda cond, vertices: model.pose(cond.as_sequence(), vertices, 0),
            fitted,
            head,
            hand,
            torch.from_numpy(offsets).float(),
            subset.cameras(tuning),
            _scaled(steps, multiple),
        )
        seconds = time.perf_counter() - started
        after = _scoring_psnr(model, tracked.params, offsets, subset.cameras(scoring))
        errors = tracking_errors(tracked.params, truth, head, hand)
        rows.append(
            [
                "avatar",
                str(steps),
                f"x{multiple:g}",
                f"{after:.2f}",
                f"{after - before:+.2f}",
                f"{seconds / len(frames):.1f}",
                *(f"{errors[k]:.2f}" for k in ERROR_KEYS),
            ]
        )
        print(rows[-1], flush=True)
    log = ResultLog("bench_test_tracking", preset=_preset(root))
    title = (
        f"rates: {root.name} {args.method} seed {args.seed}, train motion frames {frames.tolist()} from the fit's "
        f"parameters; tuning {','.join(tuning)}, scoring {','.join(scoring)}"
    )
    headers = ("tracking", "steps", "rates", "PSNR scoring", "gain", "s/frame", *ERROR_LABELS)
    print(title)
    print(log.table(title, headers, rows))
    log.write(args.results)


def cross(args: argparse.Namespace) -> None:
    """A ground-truth-trained avatar tracks the held-out motion from another workspace's fit (its poses, with its
    shapes or the truth's): how much of the fit's gap the avatar tracking closes when the avatar is not to blame."""
    torch.set_num_threads(1)
    trained, fitted_root = args.trained.resolve(), args.fitted.resolve()
    head, hand = procedural_head(), procedural_hand()
    dynamic = trained / "methods" / method_run(args.method, args.seed) / "dynamic"
    model = load_trained(dynamic)
    uses_pbd = bool(json.loads((dynamic / "_manifest.json").read_text())["config"]["method.pbd"])
    views = load_views(trained / "capture", trained / "frames", "test", "train")
    tuning, scoring = tracking_cameras("auto", views.camera_ids)
    truth = load_ground_truth_params(trained / "capture", "test")

    def offsets(root: Path) -> np.ndarray:
        shape = (views.num_frames, head.num_vertices, 3)
        return load_face_offsets(root / "pbd", "test", *shape[:2]) if uses_pbd else np.zeros(shape)

    at_truth = _scoring_psnr(model, truth, offsets(trained), views.cameras(scoring))
    rows = [["truth", "the truth's", f"{at_truth:.2f}", "0.00", "0.00", "0.00"]]
    for shapes in ("the fit's", "the truth's"):
        fitted = load_params(fitted_root / "fit", "test")
        if shapes == "the truth's":
            fitted = {**fitted, "flame_shape": truth["flame_shape"], "mano_shape": truth["mano_shape"]}
        start = _scoring_psnr(model, fitted, offsets(fitted_root), views.cameras(scoring))
        tracked = track_with_avatar(
            lambda cond, vertices: model.pose(cond.as_sequence(), vertices, 0),
            fitted,
            head,
            hand,
            torch.from_numpy(offsets(fitted_root)).float(),
            views.cameras(tuning),
            AvatarTrackingConfig(),
        )
        after = _scoring_psnr(model, tracked.params, offsets(fitted_root), views.cameras(scoring))
        for label, params, value in (("fit", fitted, start), ("avatar", tracked.params, after)):
            errors = tracking_errors(params, truth, head, hand)
            rows.append([label, shapes, f"{value:.2f}", *(f"{errors[k]:.2f}" for k in ERROR_KEYS)])
        print(rows[-2:], flush=True)
    log = ResultLog("bench_test_tracking", preset=_preset(trained))
    title = (
        f"cross: {trained.name} {args.method} seed {args.seed} trained on ground-truth tracking, the held-out motion "
        f"from {fitted_root.parent.name}'s fit; tuning {','.join(tuning)}, scoring {','.join(scoring)}"
    )
    print(log.table(title, ("poses", "shapes", "PSNR scoring", *ERROR_LABELS), rows))
    log.write(args.results)


ERROR_KEYS = ("mpjpe_hand_mm", "mpjpe_face_mm", "vertex_error_face_mm")
ERROR_LABELS = ("hand MPJPE", "face landmarks", "face vertices")
COLUMNS = (
    ("NV", "novel_view_psnr"),
    ("SR tracker", "self_reenact_psnr"),
    ("SR tracker, scoring", "self_reenact_scoring_psnr"),
    ("SR avatar", "self_reenact_tracked_psnr"),
)


def _stat(values: list[float]) -> str:
    if not values:
        return "-"
    v = np.asarray(values)
    return f"{v.mean():.2f}" if len(v) == 1 else f"{v.mean():.2f} ± {v.std(ddof=1):.2f}"


def _evaluations(outputs: Path, subject: str, method: str) -> list[dict]:
    """The evaluate manifests' metrics of ``method`` per seed found (seeds 0-9), with the avatar tracking."""
    found = []
    for seed in range(10):
        path = outputs / subject / "methods" / method_run(method, seed) / "evaluate" / "_manifest.json"
        if path.is_file():
            metrics = json.loads(path.read_text())["metrics"]
            if "self_reenact_tracked_psnr" in metrics:
                found.append({"seed": seed, **metrics})
    return found


def table(args: argparse.Namespace) -> None:
    arms = dict(a.split("=", 1) for a in args.arm)
    reference = args.reference or next(iter(arms))
    log = ResultLog("bench_test_tracking", preset=_preset(Path(next(iter(arms.values()))) / args.subject[0]))
    rows, gaps, errors = [], [], []
    for subject in args.subject:
        for method in METHODS:
            found = {arm: _evaluations(Path(d), subject, method) for arm, d in arms.items()}
            for arm, runs in found.items():
                if runs:
                    rows.append(
                        [subject, method, arm, ",".join(str(r["seed"]) for r in runs)]
                        + [_stat([r[key] for r in runs]) for _, key in COLUMNS]
                    )
                    errors.append(
                        [subject, method, arm]
                        + [
                            f"{np.mean([r[f'tracking_{when}_{k}'] for r in runs]):.2f}"
                            for k in ERROR_KEYS
                            for when in ("before", "after")
                        ]
                    )
            ref = found.get(reference) or []
            for arm, runs in found.items():
                if arm == reference or not runs or not ref:
                    continue
                mean = lambda rs, k: float(np.mean([r[k] for r in rs]))  # noqa: E731
                gaps.append(
                    [subject, method, arm]
                    + [f"{mean(runs, k) - mean(ref, k):+.2f}" for _, k in COLUMNS]
                    + [f"{mean(runs, 'self_reenact_tracked_psnr') - mean(ref, 'self_reenact_scoring_psnr'):+.2f}"]
                )
    headers = ("subject", "method", "tracking", "seeds", *(label for label, _ in COLUMNS))
    title = "Full-image PSNR (dB), mean ± sd over the seeds; SR scoring / avatar: the scoring training cameras only"
    print(log.table(title, headers, rows))
    gap_title = f"Each arm minus '{reference}' (full-image PSNR dB; last: SR avatar minus the reference's SR tracker)"
    print(
        log.table(
            gap_title,
            ("subject", "method", "tracking", *(label for label, _ in COLUMNS), "SR avatar - ref. tracker"),
            gaps,
        )
    )
    err_title = "The held-out motion's 3D errors (mm, mean over seeds): the fit's -> tracked by the avatar"
    err_headers = (
        "subject",
        "method",
        "tracking",
        *(f"{label} {w}" for label in ERROR_LABELS for w in ("fit", "avatar")),
    )
    print(log.table(err_title, err_headers, errors))
    log.write(args.results)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("rates", help="choose the settings on the train motion's training views")
    r.add_argument("--workspace", type=Path, required=True, help="a subject's folder: OUT/<setting>/<subject>")
    r.add_argument("--method", default="interactavatar")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--frames", type=int, default=6, help="train-motion frames, evenly spaced")
    r.add_argument("--sweep", nargs="*", help="settings STEPSxMULTIPLE of the defaults (default: 40x1 20x1 ...)")
    add_results_argument(r)
    t = sub.add_parser("table", help="table the evaluated workspaces")
    t.add_argument("--arm", action="append", required=True, help="LABEL=OUTPUTS of a bench_seeds setting")
    t.add_argument("--subject", action="append", required=True)
    t.add_argument("--reference", help="the arm the others are compared with (default: the first)")
    add_results_argument(t)
    c = sub.add_parser("cross", help="a ground-truth-trained avatar tracks another workspace's fitted motion")
    c.add_argument("--trained", type=Path, required=True, help="OUT/<ground-truth setting>/<subject>")
    c.add_argument("--fitted", type=Path, required=True, help="OUT/<fitted setting>/<subject>")
    c.add_argument("--method", default="interactavatar")
    c.add_argument("--seed", type=int, default=0)
    add_results_argument(c)
    args = parser.parse_args()
    {"rates": rates, "table": table, "cross": cross}[args.command](args)


if __name__ == "__main__":
    main()
