"""Quality against time per preset: held-out-camera and held-out-motion metrics of the warm-up avatar.

Runs capture -> frames -> warmup -> dynamic -> evaluate for each preset into a temporary
directory (or ``--outputs``) and prints one row per preset: warm-up steps and
wall time, Gaussians, and PSNR / SSIM / LPIPS on the novel view (all frames and
frames without contact) and on self-reenactment; then the dynamic model's novel-view and self-reenactment PSNR (its
comparison at equal steps is ``bench_dynamic.py``). Goal (issue 4): novel-view
PSNR >= 28 dB on frames without contact at ``standard``.

Usage: python benchmarks/bench_quality.py [--presets smoke draft standard] [--outputs DIR] [--fit-source S]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from pipeline.config import validate_config  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from stages import REGISTRY  # noqa: E402


def run_preset(preset: str, outputs: Path, fit_source: str) -> tuple:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[f"quality={preset}", f"paths.outputs={outputs / preset}",
                                           "run.until=evaluate", "run.progress=false", f"fit.source={fit_source}"])
    cfg = validate_config(cfg, REGISTRY)
    t0 = time.perf_counter()
    Runner(cfg, REGISTRY, log=lambda _m: None).run()
    total = time.perf_counter() - t0
    root = outputs / preset / cfg.subject
    warm = json.loads((root / "warmup" / "_manifest.json").read_text())
    dyn = json.loads((root / "dynamic" / "_manifest.json").read_text())
    ev = json.loads((root / "evaluate" / "_manifest.json").read_text())["metrics"]
    static = {k.removeprefix("gaussian_avatars_"): v for k, v in ev.items() if k.startswith("gaussian_avatars_")}
    return (preset, warm["metrics"]["steps"], warm["metrics"]["gaussians"], f"{warm['timings']['wall_s']:.0f}",
            f"{dyn['timings']['wall_s']:.0f}", f"{total:.0f}", static["novel_view_psnr"],
            static.get("novel_view_psnr_no_contact", float("nan")), static["novel_view_ssim"],
            static["novel_view_lpips"], static["self_reenact_psnr"], static["self_reenact_lpips"],
            ev["novel_view_psnr"], ev["self_reenact_psnr"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["smoke", "draft"])
    parser.add_argument("--outputs", type=Path, default=None, help="keep artifacts here (default: a temp dir)")
    parser.add_argument("--fit-source", default="ground_truth",
                        help="fit.source: ground_truth (default) measures the avatar apart from fitting error")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        outputs = args.outputs or Path(tmp)
        rows = [run_preset(p, outputs, args.fit_source) for p in args.presets]
    print(format_table(("preset", "steps", "Gaussians", "warm-up s", "stage two s", "DAG s", "NV PSNR",
                        "NV PSNR no-contact", "NV SSIM", "NV LPIPS", "SR PSNR", "SR LPIPS", "dynamic NV PSNR",
                        "dynamic SR PSNR"), rows))


if __name__ == "__main__":
    main()
