"""Quality against time per preset: held-out-camera and held-out-motion metrics of the static avatar.

Runs capture -> frames -> warmup -> dynamic -> evaluate for each preset and the methods gaussian_avatars
(static Gaussians, warm-up plus stage-two steps) and interactavatar into a temporary directory (or
``--outputs``) and prints one row per preset: warm-up steps and the GaussianAvatars stages' wall time,
Gaussians, and its PSNR / SSIM / LPIPS on the novel view (all frames and frames without contact) and on
self-reenactment; then the full model's novel-view and self-reenactment PSNR (all methods side by side:
``make compare``). Goal (issue 4): novel-view
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


def run_method(preset: str, outputs: Path, fit_source: str, method: str) -> tuple[dict, dict, dict, float]:
    """Run the DAG until evaluate for one method; (warm-up, dynamic, evaluate manifests, wall s)."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[f"quality={preset}", f"paths.outputs={outputs / preset}",
                                           "run.until=evaluate", "run.progress=false", f"fit.source={fit_source}",
                                           f"method={method}"])
    cfg = validate_config(cfg, REGISTRY)
    t0 = time.perf_counter()
    Runner(cfg, REGISTRY, log=lambda _m: None).run()
    total = time.perf_counter() - t0
    root = outputs / preset / cfg.subject / "methods" / method
    manifests = [json.loads((root / s / "_manifest.json").read_text()) for s in ("warmup", "dynamic", "evaluate")]
    return (*manifests, total)


def run_preset(preset: str, outputs: Path, fit_source: str) -> tuple:
    """One table row: the GaussianAvatars baseline's quality and cost, and the full model's PSNR."""
    warm, dyn, static_ev, static_s = run_method(preset, outputs, fit_source, "gaussian_avatars")
    _, _, full_ev, full_s = run_method(preset, outputs, fit_source, "interactavatar")
    static, ev, total = static_ev["metrics"], full_ev["metrics"], static_s + full_s
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
    print(format_table(("preset", "warm-up steps", "Gaussians", "warm-up s", "stage two s", "DAG s", "GA NV PSNR",
                        "GA NV PSNR no-contact", "GA NV SSIM", "GA NV LPIPS", "GA SR PSNR", "GA SR LPIPS",
                        "full NV PSNR", "full SR PSNR"), rows))


if __name__ == "__main__":
    main()
