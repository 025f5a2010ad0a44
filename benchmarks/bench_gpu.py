"""``make test-gpu``: the CUDA (gsplat) backend checked and measured on a GPU machine, in one table.

1. gsplat's CUDA extension: built (gsplat compiles it just in time on first use, minutes) and loaded;
2. the ``cuda``-marked tests (``tests/render/gaussians``: the adapter against the project's backends and the
   extremes, through gsplat's CUDA kernels);
3. ``bench_rasterizer.py --backend gsplat``'s table: gsplat beside the compiled cpu backend, ms per forward +
   backward, peak memory, and gsplat's image against the cpu backend's;
4. the smoke DAG up to ``evaluate`` twice into one outputs folder: with the rasterizer ``auto`` (the compiled
   cpu backend: training runs on CPU tensors) and with ``backend=gsplat`` for the warm-up, stage two and the
   evaluation (the method named ``interactavatar_gsplat``; the CPU tensors are copied to the GPU to render);
   the shared stages run once. Per arm: ms per step of the warm-up and of stage two, and the held-out PSNR
   (novel view and self-reenactment, full image), with gsplat's difference to the cpu arm.

Never part of the default suite (CI has no GPU). Writes ``--json`` (default
``benchmarks/results/bench_gpu.json``) with the commit, machine and every figure.

Usage: python benchmarks/bench_gpu.py [--outputs DIR] [--json PATH] [--skip-dag] [--quick] [--set KEY=VALUE ...]
       [--deadline-s S]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks.provenance import commit, cpu_name  # noqa: E402

sys.path.insert(0, str(REPO / "benchmarks"))

import torch  # noqa: E402

from pipeline.summary import format_table  # noqa: E402

#: arm -> (method name, overrides); gsplat first, so that a deadline drops the reference arm, not the one checked
ARMS = {
    "gsplat": (
        "interactavatar_gsplat",
        ["method.name=interactavatar_gsplat"]
        + [f"stage.{stage}.backend=gsplat" for stage in ("warmup", "dynamic", "evaluate", "reenact")],
    ),
    "cpu": ("interactavatar", []),
}


def build_gsplat() -> dict:
    """Load gsplat's CUDA extension (building it the first time); seconds and whether it loaded."""
    t0 = time.perf_counter()
    try:
        from gsplat.cuda import _backend

        loaded, error = _backend._C is not None, ""
    except Exception as exc:  # any build failure is reported, not raised
        loaded, error = False, f"{type(exc).__name__}: {exc}"
    return {"gsplat_build_s": time.perf_counter() - t0, "gsplat_loaded": loaded, "gsplat_error": error[-2000:]}


def run_cuda_tests(log: Path) -> dict:
    """The cuda-marked tests of the rasterizer; their pytest summary line and exit code, the whole output in
    ``log``."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-m", "cuda", "-p", "no:cacheprovider", "tests/render/gaussians"],
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


def run_arm(arm: str, outputs: Path, extra: list[str] = ()) -> dict:
    """The smoke DAG up to evaluate for one arm; its wall time, ms per step and held-out PSNR."""
    from hydra import compose, initialize_config_dir

    from data_schemas.metrics import METRICS
    from data_schemas.tables import read_table
    from pipeline.config import validate_config
    from pipeline.runner import Runner
    from stages import REGISTRY

    method, overrides = ARMS[arm]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "quality=smoke",
                f"paths.outputs={outputs}",
                "run.until=evaluate",
                "run.progress=false",
                *overrides,
                *extra,
            ],
        )
    cfg = validate_config(cfg, REGISTRY)
    t0 = time.perf_counter()
    Runner(cfg, REGISTRY, log=lambda _m: None).run()
    wall = time.perf_counter() - t0
    root = outputs / cfg.subject / "methods" / method
    manifests = {s: json.loads((root / s / "_manifest.json").read_text()) for s in ("warmup", "dynamic")}
    warm = manifests["warmup"]
    metrics = read_table(root / "evaluate" / "metrics.parquet", METRICS)
    psnr = {}
    for split in ("novel_view", "self_reenact"):
        values = [
            p
            for p, s, r, m in zip(metrics["psnr"], metrics["split"], metrics["region"], metrics["method"])
            if s == split and r == "full" and m == method
        ]
        psnr[split] = float(sum(values) / len(values))
    return {
        "wall_s": wall,
        "warmup_ms_per_step": 1000 * warm["timings"]["wall_s"] / warm["metrics"]["steps"],
        "dynamic_ms_per_step": manifests["dynamic"]["metrics"]["ms_per_step"],
        "psnr_novel_view": psnr["novel_view"],
        "psnr_self_reenact": psnr["self_reenact"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, default=REPO / "outputs" / "gpu_check")
    parser.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "bench_gpu.json")
    parser.add_argument("--skip-dag", action="store_true", help="no smoke DAG (build, tests and rasterizer only)")
    parser.add_argument("--quick", action="store_true", help="the rasterizer at its --quick sizes, 3 repeats")
    parser.add_argument("--skip-rasterizer", action="store_true", help="no gsplat-beside-cpu timing")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="overrides for both DAG arms, e.g. stage.dynamic.patch_weight=0",
    )
    parser.add_argument(
        "--deadline-s",
        type=float,
        default=None,
        help="start no DAG arm after this many seconds (the arms left are recorded as skipped)",
    )
    args = parser.parse_args()
    start = time.perf_counter()
    if not torch.cuda.is_available():
        raise SystemExit("bench_gpu needs a CUDA GPU (torch.cuda.is_available() is False)")
    from avatar.render.gaussians import available_backends

    result: dict = {
        "commit": commit(),
        "dag_overrides": args.set,
        "machine": platform.node(),
        "cpu": cpu_name(),
        "gpu": torch.cuda.get_device_name(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "cpus": os.cpu_count(),
        "load_start": os.getloadavg(),
    }

    def save() -> None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))

    result.update(build_gsplat())
    print(
        f"gsplat CUDA extension: loaded={result['gsplat_loaded']} in {result['gsplat_build_s']:.0f} s "
        f"{result['gsplat_error']}",
        flush=True,
    )
    result["backends"] = available_backends()
    save()
    result.update(run_cuda_tests(args.json.with_name(args.json.stem + "_tests.log")))
    print(f"cuda tests: {result['tests_summary']} ({result['tests_s']:.0f} s)", flush=True)
    save()
    if "gsplat" in result["backends"] and not args.skip_rasterizer:
        import bench_rasterizer

        configs = bench_rasterizer.QUICK if args.quick else bench_rasterizer.FULL
        try:
            result["rasterizer"] = bench_rasterizer.gsplat_beside_cpu(configs, 3 if args.quick else 5)
        except Exception as exc:  # recorded; the DAG check still runs
            result["rasterizer_error"] = f"{type(exc).__name__}: {exc}"
        save()
    if not args.skip_dag and "gsplat" in result["backends"]:
        result["dag"] = {}
        for arm in ARMS:
            if args.deadline_s is not None and time.perf_counter() - start > args.deadline_s:
                result["dag"][arm] = {"skipped": f"past the {args.deadline_s:.0f} s deadline"}
                continue
            try:
                result["dag"][arm] = run_arm(arm, args.outputs, args.set)
            except Exception as exc:  # recorded; the other arm still runs
                result["dag"][arm] = {"skipped": f"failed: {type(exc).__name__}: {exc}"}
            print(f"smoke DAG, {arm} arm: {result['dag'][arm]}", flush=True)
            save()
    result["load_end"] = os.getloadavg()
    save()
    print_table(result)


def print_table(result: dict) -> None:
    """The one table ``make test-gpu`` prints."""
    rows = [
        ("GPU / torch / CUDA", f"{result['gpu']} / {result['torch']} / {result['cuda']}"),
        (
            "gsplat extension",
            f"{'loaded' if result['gsplat_loaded'] else 'FAILED'} ({result['gsplat_build_s']:.0f} s to build or load)",
        ),
        ("cuda-marked tests", result["tests_summary"]),
    ]
    if "rasterizer_error" in result:
        rows.append(("rasterizer", result["rasterizer_error"]))
    for r in result.get("rasterizer", []):
        rows.append(
            (
                f"rasterizer {r['image']}x{r['image']}, {r['gaussians'] // 1000}k: cpu / gsplat ms (x faster)",
                f"{r['cpu_ms']:.1f} / {r['gsplat_ms']:.2f} ({r['speedup']:.0f}x); image vs cpu "
                f"PSNR {r['psnr_vs_cpu']:.1f} dB, max |rgb| {r['max_rgb_diff']:.1e}",
            )
        )
    dag = {arm: r for arm, r in result.get("dag", {}).items() if "skipped" not in r}
    for arm, r in result.get("dag", {}).items():
        if "skipped" in r:
            rows.append((f"smoke DAG, {arm} arm", r["skipped"]))
    if len(dag) == 2:
        for key, label, fmt in (
            ("warmup_ms_per_step", "warm-up ms/step", "{:.1f}"),
            ("dynamic_ms_per_step", "stage two ms/step", "{:.1f}"),
            ("psnr_novel_view", "novel view PSNR dB", "{:.2f}"),
            ("psnr_self_reenact", "self-reenactment PSNR dB", "{:.2f}"),
            ("wall_s", "DAG wall s (the first arm includes the shared stages)", "{:.0f}"),
        ):
            cpu, gs = dag["cpu"][key], dag["gsplat"][key]
            rows.append(
                (
                    f"smoke DAG {label}: cpu / gsplat",
                    f"{fmt.format(cpu)} / {fmt.format(gs)} (gsplat - cpu {gs - cpu:+.2f})",
                )
            )
    elif dag:
        rows += [(f"smoke DAG, {arm} arm", ", ".join(f"{k} {v:.2f}" for k, v in r.items())) for arm, r in dag.items()]
    rows.append(("load average start / end", f"{result['load_start'][0]:.2f} / {result['load_end'][0]:.2f}"))
    print(format_table(("check", "result"), rows))


if __name__ == "__main__":
    main()
