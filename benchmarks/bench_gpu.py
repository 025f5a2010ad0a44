"""Training on a GPU (``run.device=cuda``), checked and measured: what ``make test-gpu`` runs, in tables (issue 58).

On a CUDA machine, in this order (each part recorded as it finishes, so that a deadline or a failure keeps the rest):

1. gsplat's CUDA extension: built (just in time, the first time) and loaded;
2. the ``cuda``-marked tests: the rasterizer adapter (``tests/render/gaussians``) and training on the device
   (``tests/gpu``: no tensor of a training loop left on the CPU, the smoke DAG end to end on the GPU, its PSNR within
   the CPU's seed spread);
3. gsplat beside the compiled cpu rasterizer (``bench_rasterizer.gsplat_beside_cpu``, ``--quick`` sizes);
4. the step costs on the GPU (``bench_dynamic.step_costs`` with ``device=cuda``): a warm-up step and a stage-two step
   of the paper's heads and of the shared heads, each also in bf16, from the same warm-up, at the presets given to
   ``--step-presets``; then a ``torch.profiler`` summary of stage-two steps at the first of them: the kernels that
   take the device's time, and the host's waits for the device per step;
5. the DAG after capture generation, per preset (``--presets``: smoke, draft, standard, paper, as far as
   ``--deadline-s`` allows) and method (InteractAvatar, GaussianAvatars), ``fit.source=ground_truth``, on the GPU:
   the wall time of every stage, ms per warm-up and stage-two step, peak device memory, PSNR and LPIPS per split; at
   smoke also on this machine's CPU in the same run, as the reference.

Every run is appended to ``benchmarks/results/bench_gpu.json`` (``--results``) with the commit, the machine, the
GPU's name and ``training_device``; ``render_results.py`` renders it as ``docs/results/bench_gpu.md``. Never part of
the default suite (CI has no GPU).

``--cpu-seeds`` runs anywhere: the smoke DAG on the CPU for seeds 0-2, whose PSNR mean and spread per split the GPU
test compares its own with (the newest such run's ``figures.cpu_smoke_seeds``).

Usage: python benchmarks/bench_gpu.py [--presets smoke draft standard paper] [--methods ...] [--deadline-s S]
                                      [--step-presets draft standard] [--skip-tests] [--skip-rasterizer]
                                      [--outputs DIR] [--results DIR] [--set KEY=VALUE ...]
       python benchmarks/bench_gpu.py --cpu-seeds [--outputs DIR]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import torch  # noqa: E402

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402

#: the stages of the DAG after capture generation, in order (those a run to ``evaluate`` computes)
STAGES = ("frames", "keypoints", "fit", "scene", "pbd", "warmup", "dynamic", "evaluate")
SPLITS = ("novel_view", "self_reenact")
#: the issue's goals on one H100 or H200
GOALS = {"step_ratio": 3.0, "draft_dag_s": 120.0, "standard_dag_s": 300.0, "paper_dag_s": 1800.0}
METHODS = ("interactavatar", "gaussian_avatars")


def build_gsplat() -> dict[str, Any]:
    """Load gsplat's CUDA extension (building it the first time); seconds and whether it loaded."""
    t0 = time.perf_counter()
    try:
        from gsplat.cuda import _backend

        loaded, error = _backend._C is not None, ""
    except Exception as exc:  # any build failure is reported, not raised
        loaded, error = False, f"{type(exc).__name__}: {exc}"
    return {"gsplat_build_s": time.perf_counter() - t0, "gsplat_loaded": loaded, "gsplat_error": error[-2000:]}


def run_cuda_tests(log: Path) -> dict[str, Any]:
    """The cuda-marked tests (rasterizer and training on the device): their pytest summary line and exit code; the
    whole output in ``log``."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-m",
            "cuda",
            "-p",
            "no:cacheprovider",
            "tests/render/gaussians",
            "tests/gpu",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    log.write_text(proc.stdout + proc.stderr)
    print("\n".join(line for line in proc.stdout.splitlines() if line.startswith(("FAILED", "ERROR", "E   "))))
    summary = (proc.stdout.strip().splitlines() or [""])[-1]
    if proc.returncode < 0:  # killed by a signal: the summary line is the progress dots so far
        summary = f"CRASHED (signal {-proc.returncode}) after {summary.count('.')} passed: {proc.stderr[:300]}"
    return {"tests_rc": proc.returncode, "tests_summary": summary, "tests_s": time.perf_counter() - t0}


def run_dag(preset: str, method: str, device: str, outputs: Path, extra: list[str], seed: int = 0) -> dict[str, Any]:
    """The DAG until ``evaluate`` of ``method`` at ``preset`` on ``device`` (``cuda`` or ``cpu``; the CPU's runs keep
    their artifacts as method ``<method>_cpu``, beside the GPU's), ground-truth tracking: every stage's wall time,
    ms per warm-up and stage-two step, the device's peak memory, and PSNR and LPIPS (full image) per split."""
    from hydra import compose, initialize_config_dir

    from data_schemas.metrics import METRICS
    from data_schemas.tables import read_table
    from pipeline.config import validate_config
    from pipeline.runner import Runner
    from pipeline.workspace import method_run
    from stages import REGISTRY

    name = method if device == "cuda" else f"{method}_cpu"
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"quality={preset}",
                f"method={method}",
                f"method.name={name}",
                f"seed={seed}",
                "fit.source=ground_truth",
                f"run.device={device}",
                f"paths.outputs={outputs / preset}",
                "run.until=evaluate",
                "run.progress=false",
                *extra,
            ],
        )
    cfg = validate_config(cfg, REGISTRY)
    t0 = time.perf_counter()
    Runner(cfg, REGISTRY, log=lambda _m: None).run()
    wall = time.perf_counter() - t0
    subject = outputs / preset / cfg.subject
    folders = {s: subject / ("methods/" + method_run(name, seed) if REGISTRY[s].per_method else "") / s for s in STAGES}
    manifests = {s: json.loads((folders[s] / "_manifest.json").read_text()) for s in STAGES}
    metrics = read_table(folders["evaluate"] / "metrics.parquet", METRICS)
    out: dict[str, Any] = {
        "preset": preset,
        "method": method,
        "training_device": device,
        "seed": seed,
        "wall_s": wall,
        "stage_s": {s: manifests[s]["timings"]["wall_s"] for s in STAGES},
        "warmup_ms_per_step": 1000 * manifests["warmup"]["timings"]["wall_s"] / manifests["warmup"]["metrics"]["steps"],
        "dynamic_ms_per_step": manifests["dynamic"]["metrics"]["ms_per_step"],
        "peak_device_mb": max(
            (manifests[s].get("device") or {}).get("peak_memory_mb", float("nan")) for s in ("warmup", "dynamic")
        ),
        "rasterizer": manifests["dynamic"]["metrics"].get("rasterizer", "-"),
    }
    out["dag_after_capture_s"] = sum(out["stage_s"].values())
    out["step_ratio"] = out["dynamic_ms_per_step"] / out["warmup_ms_per_step"]
    for split in SPLITS:
        rows = [
            i
            for i, (s, r, m) in enumerate(zip(metrics["split"], metrics["region"], metrics["method"]))
            if s == split and r == "full" and m == name
        ]
        out[f"psnr_{split}"] = float(statistics.fmean(float(metrics["psnr"][i]) for i in rows))
        out[f"lpips_{split}"] = float(statistics.fmean(float(metrics["lpips"][i]) for i in rows))
    return out


def profile_stage_two(preset: str, outputs: Path, extra: list[str], steps: int = 10) -> dict[str, Any]:
    """``torch.profiler`` over ``steps`` stage-two steps on the GPU from the cached warm-up at ``preset`` (after 3
    untimed steps): the top operators by device time, and per step the host's waits for the device
    (``cudaStreamSynchronize``, ``cudaDeviceSynchronize``) and its copies (``cudaMemcpyAsync``)."""
    from bench_dynamic import stage_two_inputs, synchronize
    from torch.profiler import ProfilerActivity, profile

    from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic

    inputs = stage_two_inputs(preset, "synth_a", outputs / preset, extra, "cuda")

    def train(n: int) -> None:
        cfg = DynamicTrainConfig(steps=n, patch_weight=inputs.patch_weight)
        train_dynamic(
            inputs.model(0), inputs.views, inputs.meshes, inputs.cond, inputs.contact, cfg, lpips=inputs.lpips
        )

    train(3)
    synchronize("cuda")
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        train(steps)
        synchronize("cuda")
    averages = prof.key_averages()
    calls = {e.key: e.count for e in averages}
    waits = sum(calls.get(k, 0) for k in ("cudaStreamSynchronize", "cudaDeviceSynchronize"))
    return {
        "preset": preset,
        "steps": steps,
        "waits_per_step": waits / steps,
        "copies_per_step": calls.get("cudaMemcpyAsync", 0) / steps,
        "kernel_launches_per_step": calls.get("cudaLaunchKernel", 0) / steps,
        "top": averages.table(sort_by="device_time_total", row_limit=15),
    }


def cpu_seeds(outputs: Path, extra: list[str], seeds: tuple[int, ...] = (0, 1, 2)) -> dict[str, Any]:
    """The smoke DAG on the CPU, InteractAvatar, ground-truth tracking, per seed: PSNR (full image) per split, and its
    mean and sample standard deviation over the seeds."""
    runs = [run_dag("smoke", "interactavatar", "cpu", outputs, extra, seed) for seed in seeds]
    return {
        split: {
            "values": [r[f"psnr_{split}"] for r in runs],
            "mean": statistics.fmean(r[f"psnr_{split}"] for r in runs),
            "sd": statistics.stdev(r[f"psnr_{split}"] for r in runs),
        }
        for split in SPLITS
    }


def dag_rows(runs: list[dict[str, Any]]) -> list[list[str]]:
    """One row per DAG run: preset, method, device, the DAG's time after capture, ms per step, the ratio, peak device
    memory, PSNR and LPIPS per split."""
    return [
        [
            r["preset"],
            r["method"],
            r["training_device"],
            f"{r['dag_after_capture_s']:.0f}",
            f"{r['warmup_ms_per_step']:.1f}",
            f"{r['dynamic_ms_per_step']:.1f}",
            f"{r['step_ratio']:.2f}",
            f"{r['peak_device_mb']:.0f}",
            *(f"{r[f'psnr_{s}']:.2f} / {r[f'lpips_{s}']:.4f}" for s in SPLITS),
        ]
        for r in runs
    ]


def stage_rows(runs: list[dict[str, Any]]) -> list[list[str]]:
    """Seconds per stage of every DAG run."""
    return [[r["preset"], r["method"], r["training_device"], *(f"{r['stage_s'][s]:.1f}" for s in STAGES)] for r in runs]


def goal_rows(runs: list[dict[str, Any]], steps: dict[str, dict[str, float]]) -> list[list[str]]:
    """The issue's goals against what was measured on the GPU (InteractAvatar)."""
    rows = []
    for preset, costs in steps.items():
        ratio = costs["ratio"]
        rows.append(
            [
                f"stage-two step / warm-up step, {preset}",
                f"<= {GOALS['step_ratio']:g}",
                f"{ratio:.2f}",
                "yes" if ratio <= GOALS["step_ratio"] else "no",
            ]
        )
    for r in runs:
        goal = GOALS.get(f"{r['preset']}_dag_s")
        if r["training_device"] == "cuda" and r["method"] == "interactavatar" and goal is not None:
            rows.append(
                [
                    f"{r['preset']} DAG after capture, s",
                    f"<= {goal:g}",
                    f"{r['dag_after_capture_s']:.0f}",
                    "yes" if r["dag_after_capture_s"] <= goal else "no",
                ]
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, default=REPO / "outputs" / "gpu_check")
    add_results_argument(parser)
    parser.add_argument("--presets", nargs="*", default=["smoke", "draft", "standard", "paper"])
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--step-presets", nargs="*", default=["draft", "standard"])
    parser.add_argument("--step-rounds", type=int, default=3)
    parser.add_argument("--skip-tests", action="store_true", help="no cuda-marked tests")
    parser.add_argument("--skip-rasterizer", action="store_true", help="no gsplat-beside-cpu timing")
    parser.add_argument("--cpu-seeds", action="store_true", help="the CPU's smoke seeds only (runs anywhere)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides for every DAG run")
    parser.add_argument(
        "--deadline-s", type=float, default=None, help="start nothing new after this many seconds (recorded as left)"
    )
    args = parser.parse_args()
    if args.cpu_seeds:
        log = ResultLog("bench_gpu", preset="smoke", seeds=(0, 1, 2))
        # the reference the GPU test reads is fp32's; another precision's seeds are kept under their own name
        precision = next((o.split("=", 1)[1] for o in args.set if o.startswith("run.precision=")), "fp32")
        key = "cpu_smoke_seeds" + ("" if precision == "fp32" else f"_{precision}")
        figures = {key: cpu_seeds(args.outputs, args.set)}
        rows = [
            [s, *(f"{v:.2f}" for v in f["values"]), f"{f['mean']:.2f}", f"{f['sd']:.2f}"]
            for s, f in figures[key].items()
        ]
        print(
            log.table(
                f"the CPU's smoke PSNR (dB, full image) per seed, InteractAvatar in {precision}, ground-truth tracking",
                ("split", "seed 0", "seed 1", "seed 2", "mean", "sd"),
                rows,
            )
        )
        log.write(args.results, training_device="cpu", figures=figures)
        return
    log = ResultLog("bench_gpu", preset=",".join(args.presets))
    if not torch.cuda.is_available():
        raise SystemExit("bench_gpu needs a CUDA GPU (torch.cuda.is_available() is False); --cpu-seeds runs anywhere")
    start = time.perf_counter()
    left: list[str] = []
    figures: dict[str, Any] = {
        "gpu": torch.cuda.get_device_name(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
    }

    def due(what: str) -> bool:
        if args.deadline_s is not None and time.perf_counter() - start > args.deadline_s:
            left.append(what)
            return False
        return True

    def attempt(what: str, work: Callable[..., Any], *positional: Any, **named: Any) -> Any:
        try:
            return work(*positional, **named)
        except Exception as exc:  # recorded; the other parts still run
            figures.setdefault("errors", {})[what] = f"{type(exc).__name__}: {exc}"[-2000:]
            print(f"{what}: {figures['errors'][what]}", flush=True)
            return None

    def save() -> None:  # every part as it ends: a deadline or a crash keeps what was measured
        (args.outputs / "bench_gpu.partial.json").write_text(json.dumps(figures, indent=1, default=str))

    args.outputs.mkdir(parents=True, exist_ok=True)
    figures.update(build_gsplat())
    print(f"gsplat: loaded={figures['gsplat_loaded']} in {figures['gsplat_build_s']:.0f} s", flush=True)
    save()
    if not args.skip_tests and due("cuda tests"):
        figures.update(run_cuda_tests(args.outputs / "bench_gpu_tests.log"))
        print(f"cuda tests: {figures['tests_summary']} ({figures['tests_s']:.0f} s)", flush=True)
        save()
    if not args.skip_rasterizer and figures["gsplat_loaded"] and due("rasterizer"):
        import bench_rasterizer

        figures["rasterizer"] = attempt("rasterizer", bench_rasterizer.gsplat_beside_cpu, bench_rasterizer.QUICK, 3)
        save()
    runs: list[dict[str, Any]] = []
    steps: dict[str, dict[str, float]] = {}
    for preset in args.presets:
        for method in args.methods:
            devices = ("cuda", "cpu") if preset == "smoke" else ("cuda",)
            for device in devices:
                if due(f"DAG {preset} {method} {device}"):
                    what = f"DAG {preset} {method} {device}"
                    run = attempt(what, run_dag, preset, method, device, args.outputs, args.set)
                    if run is not None:
                        runs.append(run)
                        print(f"DAG {preset} {method} {device}: {run['dag_after_capture_s']:.0f} s", flush=True)
                    figures["dag"] = runs
                    save()
        if preset in args.step_presets and due(f"step costs {preset}"):
            from bench_dynamic import step_costs

            variants = ("per_parameter", "shared", "per_parameter+bf16", "shared+bf16")
            extra = ["fit.source=ground_truth", *args.set]
            costs = attempt(
                f"step costs {preset}",
                step_costs,
                preset,
                "synth_a",
                args.outputs / preset,
                extra,
                20,
                args.step_rounds,
                heads=variants,
                device="cuda",
            )
            if costs is not None:
                steps[preset] = costs
                figures.setdefault("step_costs", {})[preset] = costs
                save()
    if steps and due("profile"):
        first = next(iter(steps))
        figures["profile"] = attempt(
            "profile", profile_stage_two, first, args.outputs, ["fit.source=ground_truth", *args.set]
        )
        save()
    figures["left_by_deadline"] = left
    gpu = figures["gpu"]
    print(
        log.table(
            f"checks on {gpu}",
            ("check", "result"),
            [
                [
                    "gsplat extension",
                    f"{'loaded' if figures['gsplat_loaded'] else 'FAILED'} ({figures['gsplat_build_s']:.0f} s)",
                ],
                ["cuda-marked tests", figures.get("tests_summary", "not run")],
                ["left by the deadline", ", ".join(left) or "-"],
                *([[k, v] for k, v in figures.get("errors", {}).items()]),
            ],
        )
    )
    if runs:
        print(
            log.table(
                f"the DAG after capture generation on {gpu} (and smoke on the CPU), ground-truth tracking, seed 0",
                (
                    "preset",
                    "method",
                    "device",
                    "DAG s",
                    "warm-up ms/step",
                    "stage two ms/step",
                    "ratio",
                    "peak device MiB",
                    *(f"{s} PSNR / LPIPS" for s in SPLITS),
                ),
                dag_rows(runs),
            )
        )
        print(log.table("seconds per stage", ("preset", "method", "device", *STAGES), stage_rows(runs)))
    for preset, costs in steps.items():
        print(
            log.table(
                f"step costs on {gpu}, {preset} (medians of {args.step_rounds} interleaved rounds of 20 steps)",
                ("variant", "ms per step", "x warm-up step"),
                [["warm-up", f"{costs['warmup_ms']:.1f}", "1.00"]]
                + [
                    [v, f"{costs[f'{v}_step_ms']:.1f}", f"{costs[f'{v}_ratio']:.2f}"]
                    for v in ("per_parameter", "shared", "per_parameter+bf16", "shared+bf16")
                ],
            )
        )
    if runs or steps:
        print(log.table(f"goals on {gpu}", ("goal", "target", "measured", "met"), goal_rows(runs, steps)))
    if figures.get("profile"):
        p = figures["profile"]
        print(
            f"\nprofile of {p['steps']} stage-two steps at {p['preset']}: {p['waits_per_step']:.1f} waits for the "
            f"device, {p['copies_per_step']:.1f} copies, {p['kernel_launches_per_step']:.0f} kernel launches per "
            f"step\n{p['top']}"
        )
    log.write(args.results, training_device="cuda", gpu=gpu, figures=figures)


if __name__ == "__main__":
    main()
