"""The runs of the methods a comparison reads: each run's metrics and run records, and whether it is stale against
the shared stages it was evaluated on."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from data_schemas.metrics import METRICS, SPLIT_SOURCES
from data_schemas.tables import read_table
from pipeline.manifest import MANIFEST_NAME
from pipeline.workspace import method_run

#: The shared (not per-method) stages that ``evaluate`` reads; a method whose evaluation read other versions of them
#: is stale. Kept equal to the DAG's by ``tests/stages/test_compare.py``.
SHARED_STAGES = ("capture", "frames", "fit", "scene", "pbd")
METRIC_NAMES = ("psnr", "ssim", "lpips")


@dataclass
class MethodRun:
    """What the comparison reads of one training run of a method (one seed): its metrics table and run
    records."""

    name: str
    seed: int
    label: str
    evaluate_dir: Path
    metrics: dict[str, np.ndarray]
    manifests: dict[str, dict[str, Any]]  # warmup, dynamic, evaluate

    @property
    def run(self) -> str:
        """The run's folder name under ``methods/`` (:func:`pipeline.workspace.method_run`)."""
        return method_run(self.name, self.seed)

    @property
    def train_steps(self) -> int:
        return int(self.manifests["warmup"]["metrics"]["steps"]) + int(self.manifests["dynamic"]["metrics"]["steps"])

    @property
    def train_wall_s(self) -> float:
        """Wall time of the warm-up and stage two, without their validation passes (``validation_s``, when
        ``stage.<stage>.validation.every`` > 0): training, not measuring it. A stage resumed after a kill counts
        the earlier run's work it resumed from too (``timings.resumed_s``: up to that run's last checkpoint)."""
        stages = [self.manifests[s] for s in ("warmup", "dynamic")]
        return sum(
            float(m["timings"]["wall_s"])
            + float(m["timings"].get("resumed_s", 0.0))
            - float(m["metrics"].get("validation_s", 0.0))
            for m in stages
        )

    @property
    def resumed(self) -> bool:
        """Whether the warm-up or stage two resumed after a kill (its time partly estimated, see train_wall_s)."""
        return any("resumed_s" in self.manifests[s]["timings"] for s in ("warmup", "dynamic"))

    @property
    def gaussians(self) -> int:
        return int(self.manifests["dynamic"]["metrics"]["gaussians"])

    @property
    def role(self) -> dict[str, Any]:
        """The method's part in the comparison, from its own config as its evaluation recorded it (``method.tables``,
        ``method.full_model``, ``method.paper``: conf/method/<name>.yaml); empty for a method that declares none."""
        return self.manifests["evaluate"].get("config", {}).get("method", {})

    def position(self, table: str) -> int | None:
        """Where the method stands in ``table`` (:data:`TABLES`), or None when it is not in it."""
        value = (self.role.get("tables") or {}).get(table)
        return None if value is None else int(value)

    def paper(self, split: str) -> dict[str, float] | None:
        """The paper's (PSNR, SSIM, LPIPS) of this method for ``split``, when the paper gives them."""
        values = (self.role.get("paper") or {}).get(split)
        return None if values is None else dict(zip(METRIC_NAMES, map(float, values)))


def split_sequences(runs: list[MethodRun]) -> dict[str, str]:
    """split -> the capture sequence it renders, from the methods' ``splits.json`` (the fixed two splits for
    evaluations written before it existed)."""
    out = {split: sequence for split, (sequence, _) in SPLIT_SOURCES.items()}
    for run in runs:
        path = run.evaluate_dir / "splits.json"
        if path.is_file():
            out |= json.loads(path.read_text())
    return out


def stage_manifest(stage_dir: Path) -> dict[str, Any]:
    return json.loads((stage_dir / MANIFEST_NAME).read_text())


def stale_reason(manifests: dict[str, dict[str, Any]], shared: dict[str, dict[str, Any]]) -> str | None:
    """Why a method's results do not belong in this comparison, or None when they do.

    ``manifests``: the method's warmup, dynamic and evaluate manifests; ``shared``: the manifests of the shared
    stages this comparison reads (:data:`SHARED_STAGES`). A method's artifacts stay on disk when a shared
    stage reruns (another preset or capture in the same outputs folder, a changed fit), and its warm-up,
    stage two and evaluation can each be rerun alone: its row belongs here only if its evaluation read
    these shared stages' outputs and the chain warm-up -> stage two -> evaluation is one run (each read the
    outputs of the one before it that are on disk now).
    """
    reads = [("evaluate", name, shared[name]) for name in SHARED_STAGES]
    reads += [("evaluate", "dynamic", manifests["dynamic"]), ("dynamic", "warmup", manifests["warmup"])]
    for reader, name, manifest in reads:
        if manifests[reader].get("upstream", {}).get(name) != manifest["output_digest"]:
            return f"its {reader} read another {name} than the one on disk now (rerun since)"
    return None


def read_run(method: str, seed: int, dirs: dict[str, Path]) -> MethodRun:
    manifests = {stage: stage_manifest(d) for stage, d in dirs.items()}
    label = manifests["evaluate"]["config"]["method"].get("label", method)
    table = read_table(dirs["evaluate"] / "metrics.parquet", METRICS)
    return MethodRun(
        method, seed, str(label), dirs["evaluate"], {k: np.asarray(v) for k, v in table.items()}, manifests
    )
