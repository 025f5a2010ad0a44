"""Rendering speed of a reenacted frame: model forward and rasterizer at several image sizes, on CPU.

Loads a method's trained model from an outputs folder (``make run`` or ``make compare`` made it), drives it
with the subject's held-out motion (contact simulated as stage ``reenact`` does) and renders an orbit view
of every frame at each ``--sizes`` (default 128, 256 and 512 px), interleaving the sizes and taking medians.
Prints one row per size and backend: model ms per frame (the same at every size), rasterizer ms per view,
frames per second, and the load average (the machine is shared). The table is appended to
``benchmarks/results/bench_reenact.json`` (``--results``) with the commit, the preset and the machine.

Usage: python benchmarks/bench_reenact.py --outputs outputs [--subject synth_a] [--method interactavatar]
       [--quality smoke] [--sizes 128 256 512] [--backends cpu torch] [--repeats 3] [--results DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from avatar.artifacts import load_params, load_scene  # noqa: E402
from avatar.reenact.cameras import orbit, orbit_intrinsics  # noqa: E402
from avatar.reenact.driving import drive  # noqa: E402
from avatar.render.gaussians import render_gaussians, resolve_backend  # noqa: E402
from avatar.representations import load_trained  # noqa: E402
from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from stages import REGISTRY  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, required=True)
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--method", default="interactavatar")
    parser.add_argument("--quality", default="smoke", help="the preset the outputs were made with")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--backends", nargs="+", default=["auto"])
    parser.add_argument("--repeats", type=int, default=3)
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_reenact", preset=args.quality)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = validate_config(
            compose(
                "config",
                overrides=[
                    f"subject={args.subject}",
                    f"method={args.method}",
                    f"quality={args.quality}",
                    f"paths.outputs={args.outputs}",
                ],
            ),
            REGISTRY,
        )
    root = args.outputs / args.subject
    model = load_trained(root / "methods" / args.method / "dynamic")
    driven = drive(cfg, load_params(root / "fit", "test"), load_scene(root / "scene"))
    vertices = driven.meshes.vertices
    points = vertices.reshape(-1, 3).numpy()
    centre = points.mean(0)
    radius = float(np.linalg.norm(points - centre, axis=1).max()) * 1.1
    eye = centre + np.array([0.0, 0.0, -6 * radius])
    T = vertices.shape[0]
    cameras = orbit(eye, centre, np.array([0.0, 1.0, 0.0]), T)
    load0 = os.getloadavg()[0]
    model_ms: list[float] = []
    render_ms: dict[tuple[int, str], list[float]] = {(s, b): [] for s in args.sizes for b in args.backends}
    background = torch.ones(3)
    with torch.no_grad():
        for _ in range(args.repeats):
            for t in range(T):
                start = time.perf_counter()
                g = model.pose(driven.cond, vertices[t], t)
                model_ms.append(1000 * (time.perf_counter() - start))
                for size in args.sizes:  # interleaved, so load changes hit every size alike
                    K = torch.tensor(orbit_intrinsics(6 * radius, radius, size), dtype=torch.float32)
                    w2c = torch.tensor(cameras[t], dtype=torch.float32)
                    for backend in args.backends:
                        start = time.perf_counter()
                        render_gaussians(
                            g.means,
                            g.quats,
                            g.scales,
                            g.opacities,
                            g.colors,
                            K,
                            w2c,
                            size,
                            size,
                            background,
                            backend=backend,
                        )
                        render_ms[(size, backend)].append(1000 * (time.perf_counter() - start))
    model_median = statistics.median(model_ms)
    rows = []
    for (size, backend), times in render_ms.items():
        median = statistics.median(times)
        rows.append(
            (
                size,
                resolve_backend(backend, vertices),
                f"{model_median:.1f}",
                f"{median:.1f}",
                f"{1000 / (model_median + median):.1f}",
                f"{1000 / median:.1f}",
            )
        )
    print(
        f"{args.method} on {args.subject} ({args.quality}): {len(g.means)} Gaussians, {T} frames x "
        f"{args.repeats}; load average {load0:.1f} -> {os.getloadavg()[0]:.1f}"
    )
    print(
        log.table(
            f"{args.method} on {args.subject}: {len(g.means)} Gaussians, held-out motion, orbit view",
            ("px", "rasterizer", "model ms/frame", "render ms/view", "fps (model + render)", "fps (render only)"),
            rows,
        )
    )
    log.write(args.results)


if __name__ == "__main__":
    main()
