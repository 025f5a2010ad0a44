"""Stage two on a CPU: the paper's heads (one MLP per Gaussian parameter) against ``stage.dynamic.heads=shared`` (one
trunk per module with a linear head per parameter), cost per preset.

``cost`` runs the DAG of one subject until the warm-up (cached in ``--outputs``), then times, in interleaved rounds
from the same warm-up Gaussians, a warm-up step and a stage-two step of each variant (``bench_dynamic.step_costs``:
medians over the rounds after an untimed one), and prints per preset the ms per step, the ratio to a warm-up step,
the speed-up of each variant and where the step's time goes (PointNet++, the MLPs' forward passes, posing and glue,
the rasterizer, the loss, the backward pass, the optimizer), with the load before and after. Each run is appended to
``benchmarks/results/bench_heads.json`` (commit, preset, machine, load), which ``render_results.py`` renders as
``docs/results/bench_heads.md``.

The quality of the two variants is measured with seeds by ``bench_seeds.py`` (settings ``h``: ground-truth tracking,
synth_a and synth_b; ``hm``: fitted MediaPipe tracking, synth_a), ``table --settings h hm --name
bench_heads_quality``.

Goal (docs/reference/quality-presets.md): a variant whose stage-two step is at most 3x a warm-up step at ``draft``
on this machine, with no region worse than ``per_parameter`` beyond the larger seed spread.

Usage: python benchmarks/bench_heads.py cost [--presets draft standard] [--subject synth_a] [--steps 20]
       [--rounds 5] [--outputs DIR] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
import torch  # noqa: E402

from avatar.nets.mlp import HEAD_KINDS  # noqa: E402
from benchmarks.bench_dynamic import VARIANTS, compose_cfg, step_costs  # noqa: E402
from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from stages import REGISTRY  # noqa: E402

#: the stage-two step this goal allows, in warm-up steps, at draft
GOAL_RATIO = 3.0


#: the parts of a stage-two step (bench_dynamic.step_costs): the profile that says where the time goes
PARTS = ("pointnet", "mlps", "posing_glue", "render", "loss", "backward", "optimizer")


def cost_table(costs: dict[str, float], variants: tuple[str, ...] = tuple(HEAD_KINDS)) -> list[list[str]]:
    """One row per variant (``heads`` or ``heads+bf16``): ms per stage-two step, the ratio to a warm-up step, the
    speed-up against the paper's heads, whether it meets the goal, and the step's parts in ms."""
    reference = costs["per_parameter_step_ms"]
    return [
        [
            kind,
            f"{costs[f'{kind}_step_ms']:.0f}",
            f"{costs[f'{kind}_ratio']:.2f}",
            f"{reference / costs[f'{kind}_step_ms']:.2f}",
            "yes" if costs[f"{kind}_ratio"] <= GOAL_RATIO else "no",
            *(f"{costs[f'{kind}_{part}_ms']:.0f}" for part in PARTS),
        ]
        for kind in variants
    ]


def cost(args: argparse.Namespace) -> None:
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    with tempfile.TemporaryDirectory() as tmp:
        base = args.outputs or Path(tmp)
        for preset in args.presets:
            outputs = base / preset
            load_before = os.getloadavg()
            cfg = compose_cfg(preset, args.subject, outputs, VARIANTS["full"][1] + args.set, until="warmup")
            Runner(cfg, REGISTRY, log=lambda _m: None).run()
            variants = tuple(HEAD_KINDS) + tuple(f"{kind}+{p}" for p in args.precisions for kind in HEAD_KINDS)
            costs = step_costs(preset, args.subject, outputs, args.set, args.steps, args.rounds, heads=variants)
            load_after = os.getloadavg()
            log = ResultLog("bench_heads", preset=preset)
            print(
                f"\n## {args.subject} at {preset}: a warm-up step {costs['warmup_ms']:.0f} ms, "
                f"{costs['gaussians']} Gaussians ({costs['hand_gaussians']} on the hand), median of {args.rounds} "
                f"interleaved rounds of {args.steps} steps; load average {load_before[0]:.2f} -> {load_after[0]:.2f}\n"
            )
            print(
                log.table(
                    f"stage-two step per variant, {args.subject}, {preset} (goal: at most {GOAL_RATIO:g}x a warm-up "
                    f"step of {costs['warmup_ms']:.0f} ms; load {load_before[0]:.2f} -> {load_after[0]:.2f})",
                    ("heads", "ms per step", "x warm-up step", "speed-up", "goal", *(f"{p} ms" for p in PARTS)),
                    cost_table(costs, variants),
                )
            )
            log.write(args.results)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("cost", help="ms per stage-two step of each variant against a warm-up step")
    c.add_argument("--presets", nargs="+", default=["draft", "standard"])
    c.add_argument("--subject", default="synth_a")
    c.add_argument("--steps", type=int, default=20, help="steps per round")
    c.add_argument("--rounds", type=int, default=5, help="interleaved rounds (medians)")
    c.add_argument("--outputs", type=Path, default=None, help="keep the warm-ups here (default: a temp dir)")
    c.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more config overrides")
    c.add_argument(
        "--precisions",
        nargs="*",
        default=[],
        choices=["bf16"],
        help="each variant also with its networks in this run.precision (rows heads+bf16)",
    )
    add_results_argument(c)
    args = parser.parse_args()
    cost(args)


if __name__ == "__main__":
    main()
