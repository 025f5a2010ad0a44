"""D-SSIM training loss, forward + backward: the shifted-sum separable filter against ``conv2d``.

Every training step of the warm-up and of stage two evaluates ``dssim_loss`` on its render (3 channels, the
crop size of the preset). The Gaussian filter of SSIM blurs 15 one-channel planes (x, y, x^2, y^2, xy per
colour). Three ways to do it, all separable (1 x 11, then 11 x 1):

- ``conv2d oneDNN``: ``F.conv2d`` with PyTorch's default CPU path (oneDNN), what the loss used before;
- ``conv2d native``: the same call with oneDNN disabled (PyTorch's own im2col + GEMM);
- ``shifted sums``: :func:`avatar.metrics.ssim._blur`, 11 scaled slices added per axis, backward by the
  adjoint filter (what the loss uses now).

The variants run interleaved, ``--repeats`` times each after a warm-up, so load from other processes hits all
alike; the table gives medians (ms per loss + backward) and the ratio of each ``conv2d`` path to the shifted
sums. Thread count and load average are printed: the numbers depend on both. The table is appended to
``benchmarks/results/bench_ssim.json`` (``--results``) with the commit and the machine.

Usage: python benchmarks/bench_ssim.py [--sizes 64 128 256 512] [--repeats 15] [--threads 1] [--results DIR]
"""

from __future__ import annotations

import argparse
import importlib
import os
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

import torch
import torch.nn.functional as F
from torch import Tensor

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402

# the module, not the function of the same name that avatar.metrics exports
ssim_module = importlib.import_module("avatar.metrics.ssim")


def conv2d_blur(x: Tensor, padding: str) -> Tensor:
    """The former filter: two one-channel ``conv2d`` calls on ``(N * K, 1, H, W)`` planes."""
    n, k, h, w = x.shape
    g = ssim_module.gaussian_window(x.dtype, x.device)
    pad = ssim_module.WINDOW_SIZE // 2 if padding == "zero" else 0
    planes = F.conv2d(x.reshape(n * k, 1, h, w), g.view(1, 1, 1, -1), padding=(0, pad))
    planes = F.conv2d(planes, g.view(1, 1, -1, 1), padding=(pad, 0))
    return planes.reshape(n, k, *planes.shape[-2:])


VARIANTS: dict[str, tuple[Callable | None, bool]] = {  # name -> (filter replacing _blur or None, oneDNN on)
    "conv2d oneDNN": (conv2d_blur, True),
    "conv2d native": (conv2d_blur, False),
    "shifted sums": (None, True),
}


def time_loss(size: int, variant: str) -> float:
    """Seconds of one ``dssim_loss`` forward + backward on a 3 x size x size render."""
    blur, onednn = VARIANTS[variant]
    gen = torch.Generator().manual_seed(size)
    pred = torch.rand(1, 3, size, size, generator=gen, requires_grad=True)
    gt = torch.rand(1, 3, size, size, generator=gen)
    patch = mock.patch.object(ssim_module, "_blur", blur) if blur is not None else nullcontext()
    with patch, torch.backends.mkldnn.flags(enabled=onednn):
        start = time.perf_counter()
        ssim_module.dssim_loss(pred, gt).backward()
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1)
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_ssim")
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore", message="TF32 acceleration")  # printed by mkldnn.flags on CPU builds
    rows = []
    for size in args.sizes:
        times: dict[str, list[float]] = {v: [] for v in VARIANTS}
        for v in VARIANTS:  # warm-up (oneDNN primitive creation, allocator)
            time_loss(size, v)
        for _ in range(args.repeats):
            for v in VARIANTS:
                times[v].append(time_loss(size, v))
        med = {v: 1000 * statistics.median(t) for v, t in times.items()}
        ref = med["shifted sums"]
        rows.append(
            (
                f"{size} x {size}",
                *(f"{med[v]:.2f}" for v in VARIANTS),
                *(f"{med[v] / ref:.1f}" for v in VARIANTS if v != "shifted sums"),
            )
        )
    load = os.getloadavg()
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), OMP_WAIT_POLICY="
        f"{os.environ.get('OMP_WAIT_POLICY', 'unset')}, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}"
    )
    print(
        log.table(
            f"D-SSIM forward + backward, median ms ({torch.get_num_threads()} thread(s), torch {torch.__version__})",
            ("render", *(f"{v} ms" for v in VARIANTS), "x oneDNN", "x native"),
            rows,
        )
    )
    log.write(args.results)


if __name__ == "__main__":
    main()
