"""Choose the patch-loss weight c (``stage.dynamic.patch_weight``) of a preset on the training views.

The paper's c = 0.1 was set for 512 px crops. On smaller crops the hand box and the hand-face overlap box are
32-48 px (``draft``) or 48-80 px (``standard``), LPIPS-VGG on such patches is about 0.14, and at c = 0.1 the
patch term is as large as the whole reconstruction loss (docs/explanation/methods.md). This benchmark
trains the full model's stage two once per candidate c, from one shared warm-up, with the same ``frames``
training frames withheld from both training stages (``stage.<warmup|dynamic>.validation``; the held-out camera
and motion are never looked at), and measures PSNR and LPIPS-alex of the withheld frames from every training
camera every ``--every`` steps.

The rule, fixed before any run: the patch loss is there for perceptual quality, and may not cost fidelity.
Among the candidates whose final validation PSNR is within ``--psnr-tolerance`` dB (0.1) of the best
candidate's, take the one with the lowest final validation LPIPS (ties: the smaller c).

Candidates live side by side as methods ``patch_w<c>`` (``patch_w0_03``) of one outputs folder, so runs may be
split over several processes (``--weights``) and the table printed afterwards with ``--no-run``.

Usage: python benchmarks/bench_patch_weight.py [--subject synth_a] [--preset draft] [--weights 0 0.01 0.03 0.1]
       [--outputs DIR] [--every 250] [--frames 4] [--psnr-tolerance 0.1] [--set KEY=VALUE ...] [--no-run]
       [--results DIR]

The tables are appended to ``benchmarks/results/bench_patch_weight.json`` (``--results``) with the commit, the
preset and the machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from data_schemas.curve import CURVE  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from stages import REGISTRY  # noqa: E402


@dataclass(frozen=True)
class Candidate:
    """One candidate weight's stage two: the validation curve (steps, PSNR dB, LPIPS) and its step cost."""

    weight: float
    steps: list[int]
    psnr: list[float]
    lpips: list[float]
    ms_per_step: float

    @property
    def final_psnr(self) -> float:
        return self.psnr[-1]

    @property
    def final_lpips(self) -> float:
        return self.lpips[-1]


def method_name(weight: float) -> str:
    """The method folder of a candidate: ``patch_w0_03`` for 0.03."""
    return "patch_w" + f"{weight:g}".replace(".", "_")  # weights are >= 0 (checked), e.g. 1e-05 -> patch_w1e-05


def overrides(
    preset: str,
    subject: str,
    outputs: Path,
    weight: float,
    warmup_steps: int,
    every: int,
    frames: int,
    extra: list[str],
) -> list[str]:
    """The full model with patch weight ``weight``; both training stages withhold the same ``frames`` frames (the
    warm-up validates only at its start and end, stage two every ``every`` steps with LPIPS)."""
    return [
        f"quality={preset}",
        f"subject={subject}",
        f"paths.outputs={outputs}",
        "run.until=dynamic",
        "run.progress=false",
        "fit.source=ground_truth",
        "method=interactavatar",
        f"method.name={method_name(weight)}",
        f"stage.dynamic.patch_weight={weight}",
        f"stage.warmup.validation.every={warmup_steps}",
        f"stage.warmup.validation.frames={frames}",
        f"stage.dynamic.validation.every={every}",
        f"stage.dynamic.validation.frames={frames}",
        "stage.dynamic.validation.lpips=true",
        *extra,
    ]


def run_candidate(args: argparse.Namespace, outputs: Path, weight: float) -> None:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        warmup_steps = int(compose("config", overrides=[f"quality={args.preset}", *args.set]).quality.warmup_steps)
        cfg = compose(
            "config",
            overrides=overrides(
                args.preset, args.subject, outputs, weight, warmup_steps, args.every, args.frames, args.set
            ),
        )
    Runner(validate_config(cfg, REGISTRY), REGISTRY, log=print).run()


def load_candidate(outputs: Path, subject: str, weight: float) -> Candidate | None:
    """A candidate's curve and cost from its stage-two folder, or None when it has not run."""
    folder = outputs / subject / "methods" / method_name(weight) / "dynamic"
    if not (folder / "_manifest.json").is_file():
        return None
    curve = read_table(folder / "curve.parquet", CURVE)
    manifest = json.loads((folder / "_manifest.json").read_text())
    return Candidate(
        weight,
        [int(s) for s in curve["step"]],
        [float(p) for p in curve["psnr"]],
        [float(v) for v in curve["lpips"]],
        float(manifest["metrics"]["ms_per_step"]),
    )


def choose(candidates: list[Candidate], psnr_tolerance_db: float) -> Candidate:
    """The rule: the lowest final LPIPS among the candidates within ``psnr_tolerance_db`` of the best final PSNR
    (ties: the smaller weight)."""
    best_psnr = max(c.final_psnr for c in candidates)
    eligible = [c for c in candidates if c.final_psnr >= best_psnr - psnr_tolerance_db]
    return min(eligible, key=lambda c: (c.final_lpips, c.weight))


def report(candidates: list[Candidate], tolerance: float, log: ResultLog) -> None:
    chosen = choose(candidates, tolerance)
    reference = min(candidates, key=lambda c: c.weight)
    rows = []
    for c in sorted(candidates, key=lambda c: c.weight):
        rows.append(
            (
                f"{c.weight:g}",
                f"{c.final_psnr:.2f}",
                f"{c.final_psnr - reference.final_psnr:+.2f}",
                f"{c.final_lpips:.4f}",
                f"{c.final_lpips - reference.final_lpips:+.4f}",
                f"{max(c.psnr):.2f}",
                f"{c.ms_per_step:.0f}",
                "<- chosen" if c is chosen else "",
            )
        )
    print(
        log.table(
            f"candidates (rule: lowest validation LPIPS within {tolerance:g} dB of the best PSNR)",
            (
                "c",
                "val PSNR",
                f"vs c={reference.weight:g}",
                "val LPIPS",
                f"vs c={reference.weight:g}",
                "best PSNR on curve",
                "ms/step",
                "",
            ),
            rows,
        )
    )
    print(
        f"\nrule: lowest validation LPIPS within {tolerance:g} dB of the best validation PSNR "
        f"({max(c.final_psnr for c in candidates):.2f} dB) -> c = {chosen.weight:g}"
    )
    curves = [
        (f"{c.weight:g}", ", ".join(f"{s}: {p:.2f}/{v:.4f}" for s, p, v in zip(c.steps, c.psnr, c.lpips, strict=True)))
        for c in sorted(candidates, key=lambda c: c.weight)
    ]
    print()
    print(log.table("validation curves", ("c", "step: PSNR / LPIPS"), curves))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--preset", default="draft")
    parser.add_argument("--weights", type=float, nargs="+", default=[0.0, 0.01, 0.03, 0.1])
    parser.add_argument("--outputs", type=Path, default=None, help="outputs folder (default: a temporary one)")
    parser.add_argument("--every", type=int, default=250, help="stage-two steps between validations")
    parser.add_argument("--frames", type=int, default=4, help="training frames withheld for validation")
    parser.add_argument("--psnr-tolerance", type=float, default=0.1, help="dB below the best PSNR still eligible")
    parser.add_argument("--set", nargs="*", default=[], help="extra Hydra overrides for every run")
    parser.add_argument("--no-run", action="store_true", help="train nothing; print the table of what is there")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_patch_weight", preset=args.preset)
    if args.no_run and args.outputs is None:
        parser.error("--no-run needs --outputs")
    if any(not math.isfinite(w) or w < 0 for w in args.weights):
        parser.error("--weights must be finite and >= 0")
    with tempfile.TemporaryDirectory() as tmp:
        outputs = args.outputs or Path(tmp)
        print(f"# preset {args.preset}, subject {args.subject}, outputs {outputs}, load {os.getloadavg()[0]:.1f}")
        if not args.no_run:
            for weight in args.weights:
                run_candidate(args, outputs, weight)
        candidates = [c for w in args.weights if (c := load_candidate(outputs, args.subject, w)) is not None]
        if not candidates:
            sys.exit(f"no candidate has run in {outputs}: run without --no-run first")
        report(candidates, args.psnr_tolerance, log)
        log.write(args.results)


if __name__ == "__main__":
    main()
