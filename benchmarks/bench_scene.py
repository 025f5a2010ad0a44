"""What the scene analysis saves: each synthetic scene modelled as the scene stage decides (``auto``) and
with every part and module forced on (``everything``), side by side.

For each scene (``dataset.scene``) and both settings it runs the DAG until ``evaluate`` for the full model
into its own outputs folder (the two settings share nothing downstream of ``fit``), alternating the settings
over ``--repeats`` rounds, and prints per run: the decisions, the wall time of the stages the decisions
touch (pbd, warmup, dynamic, evaluate; medians over the rounds), hand Gaussians, interaction-MLP
evaluations, PBD frames simulated, and the held-out PSNR (novel view: held-out camera; self-reenactment:
held-out motion). Goal (issue 15): ``auto`` within 0.2 dB of ``everything`` on held-out PSNR, in less time.

Usage: python benchmarks/bench_scene.py [--preset smoke] [--scenes no_contact face_only] [--repeats 1]
       [--overrides stage.warmup.seed=1 ...] [--results DIR]

The table is appended to ``benchmarks/results/bench_scene.json`` (``--results``) with the commit, the preset
and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from data_schemas.gaussians import BOUND_GAUSSIANS  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from stages import REGISTRY  # noqa: E402

TIMED = ("pbd", "warmup", "dynamic", "evaluate")
SETTINGS = {
    "auto": [],
    "everything": [f"stage.scene.{d}=true" for d in ("model_hand", "model_pbd", "model_interaction")],
}


def run(preset: str, scene: str, setting: str, outputs: Path, fit_source: str, extra: list[str]) -> dict:
    """One DAG run until evaluate (forced, so a repeat recomputes); its manifests and the scene's decisions."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"quality={preset}",
                f"paths.outputs={outputs}",
                f"dataset.scene={scene}",
                f"fit.source={fit_source}",
                "run.until=evaluate",
                "run.progress=false",
                "stage.capture.cross_reenactment=false",
                *SETTINGS[setting],
                *extra,
            ],
        )
    Runner(validate_config(cfg, REGISTRY), REGISTRY, log=lambda _m: None).run()
    root = outputs / cfg.subject
    folder = {s: root / s if s == "pbd" else root / "methods" / "interactavatar" / s for s in TIMED}
    manifests = {s: json.loads((folder[s] / "_manifest.json").read_text()) for s in TIMED}
    parts = read_table(folder["warmup"] / "gaussians.parquet", BOUND_GAUSSIANS)["part"]
    return {
        "scene": json.loads((root / "scene" / "scene.json").read_text()),
        "manifests": manifests,
        "hand_gaussians": sum(p == "hand" for p in parts),
    }


def _force_rerun(outputs: Path) -> None:
    """Remove the timed stages' artifacts so the next round recomputes them (the upstream stays cached)."""
    for path in outputs.glob("*/pbd"):
        shutil.rmtree(path)
        shutil.rmtree(path.parent / "methods", ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="smoke")
    parser.add_argument("--scenes", nargs="+", default=["no_contact", "face_only"])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--fit-source", default="ground_truth")
    parser.add_argument("--outputs", type=Path, default=None, help="keep artifacts here (default: a temp dir)")
    parser.add_argument("--overrides", nargs="*", default=[], help="more config overrides, e.g. stage.warmup.seed=1")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_scene", preset=args.preset)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = args.outputs or Path(tmp)
        for scene in args.scenes:
            runs: dict[str, list[dict]] = {s: [] for s in SETTINGS}
            for _ in range(args.repeats):
                for setting in SETTINGS:  # interleaved: the machine's load hits both alike
                    outputs = base / scene / setting
                    _force_rerun(outputs)
                    runs[setting].append(run(args.preset, scene, setting, outputs, args.fit_source, args.overrides))
            reference = statistics.median(
                sum(r["manifests"][s]["timings"]["wall_s"] for s in TIMED) for r in runs["everything"]
            )
            for setting, results in runs.items():
                last = results[-1]
                m = {s: last["manifests"][s]["metrics"] for s in TIMED}
                wall = statistics.median(sum(r["manifests"][s]["timings"]["wall_s"] for s in TIMED) for r in results)
                decided = "".join(
                    k[6].upper() if last["scene"][k] else "-" for k in ("model_hand", "model_pbd", "model_interaction")
                )
                rows.append(
                    (
                        scene,
                        setting,
                        decided,
                        f"{wall:.0f}",
                        f"{wall / reference:.2f}",
                        last["hand_gaussians"],
                        m["dynamic"].get("interaction_mlp_evaluations", 0),
                        m["pbd"]["simulated_frames"],
                        f"{m['evaluate']['novel_view_psnr']:.2f}",
                        f"{m['evaluate']['self_reenact_psnr']:.2f}",
                    )
                )
    load = os.getloadavg()
    print(
        f"preset {args.preset}, fit.source={args.fit_source}, {' '.join(args.overrides)}, {args.repeats} round(s), "
        f"load average {load[0]:.1f} / {load[1]:.1f}"
    )
    print(
        log.table(
            f"auto against everything (fit.source={args.fit_source}, {args.repeats} round(s) "
            f"{' '.join(args.overrides)})".replace(" )", ")"),
            (
                "scene",
                "setting",
                "modelled (H P I)",
                "pbd+warmup+dynamic+evaluate s",
                "x everything",
                "hand Gaussians",
                "I evaluations",
                "PBD frames",
                "NV PSNR",
                "SR PSNR",
            ),
            rows,
        )
    )
    log.write(args.results)


if __name__ == "__main__":
    main()
