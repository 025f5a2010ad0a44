"""Training with the compiled CPU backend reaches the quality of training with the torch backend.

The two backends differ only by float32 rounding, which training amplifies a little (density
control thresholds, Adam), so the comparison is on the result: PSNR within 0.05 dB.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.metrics.psnr import psnr
from avatar.render.gaussians.extension import cpu_extension_available, unavailable_reason
from avatar.representations.bound.warmup import render_frame, train_warmup
from data_schemas.metrics import METRICS
from data_schemas.tables import read_table
from tests.conftest import run_cli
from tests.training.test_warmup_training import CFG, _model, _scene

pytestmark = pytest.mark.skipif(
    not cpu_extension_available(), reason=f"compiled CPU rasterizer not built: {unavailable_reason()}"
)
PSNR_TOLERANCE_DB = 0.05


def _toy_psnr(backend: str) -> float:
    """Mean PSNR over every view and frame of the toy scene after 60 warm-up steps with ``backend``."""
    views, meshes = _scene()
    model = _model(meshes)
    train_warmup(model, views, meshes, dataclasses.replace(CFG, steps=60, backend=backend))
    values = []
    with torch.no_grad():
        for frame in range(views.num_frames):
            for camera in range(views.num_cameras):
                out, _ = render_frame(model, meshes, views, frame, camera, backend)
                gt = views.images[frame, camera].permute(2, 0, 1).float() / 255
                values.append(float(psnr(out.rgb.permute(2, 0, 1).clamp(0, 1), gt)))
    return float(np.mean(values))


def test_toy_warmup_reaches_the_torch_backend_psnr() -> None:
    """The short version, in the default suite: a toy scene, its training views."""
    torch_psnr, cpu_psnr = _toy_psnr("torch"), _toy_psnr("cpu")
    assert torch_psnr > 10.0  # it learned something: a flat grey guess scores ~8 dB
    assert abs(cpu_psnr - torch_psnr) <= PSNR_TOLERANCE_DB, (torch_psnr, cpu_psnr)


def _held_out_psnr(subject_dir: Path) -> dict[str, float]:
    """Mean full-image PSNR of the warm-up model per held-out split of a subject's ``evaluate`` stage."""
    metrics = read_table(subject_dir / "methods" / "gaussian_avatars" / "evaluate" / "metrics.parquet", METRICS)
    full = np.asarray(metrics["region"]) == "full"
    splits = np.asarray(metrics["split"])
    psnrs = np.asarray(metrics["psnr"], dtype=np.float64)
    return {s: float(psnrs[full & (splits == s)].mean()) for s in sorted(set(splits[full]))}


@pytest.mark.slow
def test_smoke_warmup_reaches_the_torch_backend_held_out_psnr(tmp_path: Path) -> None:
    """The DAG at quality=smoke up to evaluate, warm-up and evaluation with each backend (~2 min)."""
    out = tmp_path / "out"
    results = {}
    for backend in ("torch", "cpu"):
        run = run_cli(
            f"paths.outputs={out}",
            "quality=smoke",
            "run.progress=false",
            "run.until=evaluate",
            f"stage.warmup.backend={backend}",
            f"stage.evaluate.backend={backend}",
            f"stage.dynamic.backend={backend}",
            "quality.dynamic_steps=0",  # the warm-up alone
            "method=gaussian_avatars",
        )
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        results[backend] = _held_out_psnr(out / "synth_a")
    assert set(results["cpu"]) == {"novel_view", "self_reenact"}
    for split, value in results["torch"].items():
        assert abs(results["cpu"][split] - value) <= PSNR_TOLERANCE_DB, (split, results)
