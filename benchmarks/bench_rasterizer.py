"""Gaussian rasterizer speed and memory: forward + backward per iteration, per backend.

Scene ("like an avatar"): N Gaussians on a sphere shell of radius 0.1 m (a head-sized 0.2 m
ball) 0.7 m in front of the camera, random rotations, scales 1-3 mm, opacities U(0, 1),
focal length 2 x image size (the ball spans ~57% of the image, like a face crop). The loss
is ``sum(rgb) + sum(depth)``, backpropagated to all five inputs.

Time: median (and min) wall time of ``--repeats`` iterations after one warm-up. Memory: in a
fresh (spawned) process per configuration, the peak increase of the RSS over the first
iteration, sampled every 2 ms by a thread (psutil; tracemalloc does not see torch's allocator,
and in a warm process freed memory stays resident); on CUDA, ``torch.cuda.max_memory_allocated``.
The torch thread count, ``OMP_WAIT_POLICY`` and the load average are printed: the numbers
depend on all three. On a shared machine where another process holds a core, OpenMP's default
spin-waiting makes multi-threaded runs collapse (10x slower, erratic); run with
``OMP_WAIT_POLICY=PASSIVE`` (or ``--threads 1``) there.

Goal: torch backend, 256 x 256, 50k Gaussians, CPU: under 0.5 s forward + backward.

Usage: python benchmarks/bench_rasterizer.py [--quick] [--repeats 3] [--threads N]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from avatar.render.gaussians import available_backends, render_gaussians  # noqa: E402
from pipeline.monitor import ResourceMonitor  # noqa: E402
from pipeline.summary import format_table  # noqa: E402

FULL = [(size, n) for size in (128, 256, 512) for n in (10_000, 50_000, 200_000)]
QUICK = [(128, 10_000), (256, 50_000)]


def avatar_scene(n: int, size: int, device: str, seed: int = 0) -> tuple[list[torch.Tensor], tuple]:
    """N avatar-like Gaussians (requiring grad) and a ``size`` x ``size`` camera."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    params = [direction * 0.1 + torch.tensor([0.0, 0.0, 0.7]), torch.randn(n, 4, generator=g),
              0.001 + 0.002 * torch.rand(n, 3, generator=g), torch.rand(n, generator=g),
              torch.rand(n, 3, generator=g)]
    f = 2.0 * size
    k = torch.tensor([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    camera = (k.to(device), torch.eye(4, device=device), size, size, torch.zeros(3, device=device))
    return [p.to(device).requires_grad_(True) for p in params], camera


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _iteration(params: list[torch.Tensor], camera: tuple, backend: str) -> Callable[[], None]:
    def run() -> None:
        for p in params:
            p.grad = None
        out = render_gaussians(*params, *camera, backend=backend)
        (out.rgb.sum() + out.depth.sum()).backward()

    return run


def peak_memory_mb(fn: Callable[[], None], device: str) -> float:
    """Peak memory increase (MiB) while ``fn`` runs: RSS sampled every 2 ms, or the CUDA allocator peak."""
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        fn()
        torch.cuda.synchronize()
        return (torch.cuda.max_memory_allocated() - base) / 2**20
    with ResourceMonitor(interval_s=0.002) as monitor:
        fn()
    return monitor.usage.rss_growth_mb


def first_iteration_memory_mb(size: int, n: int, backend: str, device: str, threads: int) -> float:
    """Peak memory (MiB) of a first forward + backward; run it in a fresh process."""
    torch.set_num_threads(threads)
    params, camera = avatar_scene(n, size, device)
    return peak_memory_mb(_iteration(params, camera, backend), device)


def measure(size: int, n: int, backend: str, device: str, repeats: int) -> dict[str, float]:
    params, camera = avatar_scene(n, size, device)
    run = _iteration(params, camera, backend)
    run()  # warm-up
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        run()
        _sync(device)
        times.append(time.perf_counter() - t0)
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        peak = pool.apply(first_iteration_memory_mb, (size, n, backend, device, torch.get_num_threads()))
    return {"median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times), "peak_mb": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"only {QUICK}")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    configs = QUICK if args.quick else FULL
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} CPUs, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
          f"load average {os.getloadavg()[0]:.2f}; backends: {', '.join(available_backends())}")

    results: dict[tuple[str, int, int], dict[str, float]] = {}
    runs = [("torch", "cpu")] + [("gsplat", "cuda")] * ("gsplat" in available_backends())
    for backend, device in runs:
        rows = []
        for size, n in configs:
            r = measure(size, n, backend, device, args.repeats)
            results[backend, size, n] = r
            rows.append((f"{size}x{size}", n, *(f"{r[k]:.0f}" for k in ("median_ms", "min_ms", "peak_mb"))))
        print(f"\n{backend} backend ({device}), forward + backward per iteration")
        print(format_table(("image", "gaussians", "median ms", "min ms", "peak MiB"), rows))
    if "gsplat" in available_backends():
        ratio = {(s, n): results["torch", s, n]["median_ms"] / results["gsplat", s, n]["median_ms"]
                 for s, n in configs}
        rows = [(f"{s}x{s}", n, f"{ratio[s, n]:.1f}") for s, n in configs]
        print("\ntorch (cpu) / gsplat (cuda) time ratio")
        print(format_table(("image", "gaussians", "ratio"), rows))
    goal = results.get(("torch", 256, 50_000))
    if goal:
        verdict = "meets" if goal["median_ms"] < 500 else "misses"
        print(f"\ngoal: torch 256x256, 50k Gaussians < 500 ms: {goal['median_ms']:.0f} ms ({verdict})")


if __name__ == "__main__":
    main()
