"""Training on a CUDA device (``run.device=cuda``): the smoke DAG end to end on the GPU, no tensor of a training loop
left on the CPU, and the GPU's quality within the CPU's seed spread. Marked ``cuda``: skipped without a GPU, run by
``make test-gpu`` (benchmarks/bench_gpu.py), never needed by the default suite."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.metrics.lpips import LPIPS
from avatar.representations.bound.dynamic_model import DynamicAvatar
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.templates import procedural_hand, procedural_head
from avatar.training.checkpoint import load_checkpoint
from avatar.training.frame_params import FrameParams, ParamLearningRates
from avatar.training.validation import ValidationConfig, Validator
from data_schemas.metrics import METRICS
from data_schemas.tables import read_table
from pipeline.manifest import MANIFEST_NAME
from tests.conftest import run_cli
from tests.representations.bound.conftest import TINY, make_scene, scene_params

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (make test-gpu)"),
]

HAND_X = [0.08, 1.0, 0.09, 0.5]


def cpu_smoke_seeds() -> dict[str, dict]:
    """The CPU's smoke PSNR over seeds 0-2 (synth_a, InteractAvatar, fit.source=ground_truth), per split: ``values``,
    ``mean`` and ``sd`` (dB), from the newest ``bench_gpu.py --cpu-seeds`` run in benchmarks/results/bench_gpu.json;
    empty when there is none."""
    runs = json.loads((Path(__file__).resolve().parents[2] / "benchmarks/results/bench_gpu.json").read_text())["runs"]
    return next((r["figures"]["cpu_smoke_seeds"] for r in reversed(runs) if "cpu_smoke_seeds" in r["figures"]), {})


def _on_cuda(tensors: object, where: str) -> list[str]:
    """The paths (below ``where``) of the tensors in a nested state that are not on a CUDA device."""
    if isinstance(tensors, torch.Tensor):
        return [] if tensors.is_cuda else [where]
    if isinstance(tensors, dict):
        return [p for k, v in tensors.items() for p in _on_cuda(v, f"{where}.{k}")]
    if isinstance(tensors, (list, tuple)):
        return [p for i, v in enumerate(tensors) for p in _on_cuda(v, f"{where}[{i}]")]
    return []


def test_no_tensor_of_the_training_loops_stays_on_the_cpu(tmp_path: Path) -> None:
    """After steps of the warm-up and of stage two on the GPU, every tensor of their models, their optimisers and
    the refined parameters (as the checkpoints hold them) is on the GPU; only the samplers' generators are the
    CPU's."""
    scene = make_scene(HAND_X)
    views, meshes, cond = scene.views.to("cuda"), scene.meshes.to("cuda"), scene.cond.to("cuda")
    head, hand = procedural_head(), procedural_hand()
    offsets = torch.zeros(len(HAND_X), scene.num_face_vertices, 3)

    def params() -> FrameParams:
        return FrameParams(scene_params(HAND_X), head, hand, offsets, ParamLearningRates(), device="cuda")

    gaussians = scene.model(TINY).gaussians.to("cuda")
    warm = WarmupTrainConfig(steps=4, densify_from=0.0, densify_until=1.0, densify_interval=0.5, checkpoint_every=4)
    validator = Validator(ValidationConfig(every=2, frames=1, lpips=True), views)
    for run in ("warmup", "dynamic"):
        (tmp_path / run).mkdir()
    train_warmup(gaussians, views, meshes, warm, tmp_path / "warmup", validator=validator, params=params())
    # stage two from the warm-up's Gaussians, built on the CPU and moved, as the representation does
    dims = {"hand_pose": cond.hand_pose.shape[1], "expression": cond.expression.shape[1]}
    m = scene.meshes
    model = DynamicAvatar.from_warmup(
        gaussians.cpu(), m.vertices[0], m.faces, m.part_names, scene.num_face_vertices, dims, TINY
    ).to("cuda")
    cfg = DynamicTrainConfig(steps=4, checkpoint_every=4, patch_min_size=16)
    train_dynamic(
        model,
        views,
        meshes,
        cond,
        np.array([True, False, True, False]),
        cfg,
        tmp_path / "dynamic",
        lpips=LPIPS("vgg"),
        validator=Validator(ValidationConfig(every=2, frames=1), views),
        params=params(),
    )
    # on the host by design: Adam's step counts (torch keeps a non-fused Adam's there) and the per-frame step counts
    # of the parameters' own Adam (read to schedule each frame's update)
    host = (".step", ".steps")
    for name in ("warmup/warmup.pt", "dynamic/dynamic.pt"):
        state = load_checkpoint(tmp_path / name, ("model", "optimizer", "params"))
        assert state is not None
        off = [p for key in ("model", "optimizer", "params") for p in _on_cuda(state[key], key) if not p.endswith(host)]
        assert not off, f"{name}: on the CPU: {off[:10]}"
    assert all(p.is_cuda for p in model.parameters()) and all(b.is_cuda for b in model.buffers())


def test_the_smoke_dag_trains_and_evaluates_on_the_gpu(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = run_cli(
        f"paths.outputs={out}",
        "quality=smoke",
        "fit.source=ground_truth",
        "run.device=cuda",
        "run.progress=false",
        timeout=1200,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    method = out / "synth_a" / "methods" / "interactavatar"
    for stage in ("warmup", "dynamic", "evaluate", "reenact", "viewer"):
        manifest = json.loads((method / stage / MANIFEST_NAME).read_text())
        assert manifest["device"]["kind"] == "cuda", stage
        assert manifest["config"]["run.device"] == "cuda", stage
    for stage in ("warmup", "dynamic", "evaluate"):
        assert json.loads((method / stage / MANIFEST_NAME).read_text())["metrics"]["rasterizer"] == "gsplat"
    metrics = read_table(method / "evaluate" / "metrics.parquet", METRICS)
    psnr = {
        split: float(
            np.mean(
                [
                    p
                    for p, s, r in zip(metrics["psnr"], metrics["split"], metrics["region"])
                    if s == split and r == "full"
                ]
            )
        )
        for split in ("novel_view", "self_reenact")
    }
    assert all(math.isfinite(v) for v in psnr.values()), psnr
    reference = cpu_smoke_seeds()
    assert reference, "benchmarks/results/bench_gpu.json has no --cpu-seeds run to compare with"
    for split, value in psnr.items():  # within the CPU's seed spread (two standard deviations, 0.3 dB at least)
        mean, sd = reference[split]["mean"], reference[split]["sd"]
        assert abs(value - mean) <= max(2 * sd, 0.3), (split, value, reference[split])
