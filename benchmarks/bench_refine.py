"""Tracking refined by the images: 3D errors and cost of each stage.fit.refine mode on a capture's train motion.

Reads a workspace in which capture, frames and keypoints have run (for instance
``interactavatar subject=synth_a quality=draft fit.source=fitted stage.keypoints.detector=mediapipe
run.until=fit``), fits the sequence's keypoints once per mode (none, silhouette, photometric) with the train
views (all of them, or ``--cameras`` for a monocular fit), and prints hand MPJPE, face landmark and vertex
errors against the capture's ground truth, the silhouette IoU and the refinement's seconds per frame per view.
Writes ``benchmarks/results/bench_refine.json`` (commit, machine, load, settings, rows).

    .venv/bin/python benchmarks/bench_refine.py --workspace outputs/synth_a
    .venv/bin/python benchmarks/bench_refine.py --workspace outputs/synth_a --cameras cam04 --modes none silhouette
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from avatar.artifacts import load_ground_truth_params, load_views  # noqa: E402
from avatar.fitting.errors import tracking_errors  # noqa: E402
from avatar.fitting.fit import (  # noqa: E402
    FitConfig,
    face_shape_columns,
    fit_sequence,
)
from avatar.fitting.observations import keypoints_by_camera  # noqa: E402
from avatar.fitting.refine import REFINE_MODES, RefineConfig, evidence_from_views  # noqa: E402
from avatar.geometry.views import ViewSet  # noqa: E402
from avatar.templates import procedural_hand, procedural_head  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from data_schemas.cameras import read_cameras  # noqa: E402
from data_schemas.capture import CaptureIndex  # noqa: E402
from data_schemas.keypoints import KEYPOINTS  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.summary import format_table  # noqa: E402

ERRORS = ("mpjpe_hand_mm", "mpjpe_face_mm", "vertex_error_hand_mm", "vertex_error_face_mm")


def _subset(views: ViewSet, camera_ids: list[str]) -> ViewSet:
    idx = [views.camera_ids.index(c) for c in camera_ids]
    return ViewSet(
        images=views.images[:, idx],
        labels=views.labels[:, idx],
        K=views.K[idx],
        world_to_cam=views.world_to_cam[idx],
        camera_ids=camera_ids,
        background=views.background,
    )


def measure(workspace: Path, sequence: str, modes: list[str], cameras: list[str] | None, detector: str) -> list[dict]:
    """One row per mode: the errors of the written parameters, the silhouette IoU and the cost."""
    head, hand = procedural_head(), procedural_hand()
    cap = workspace / "capture"
    info = CaptureIndex.read(cap).sequences[sequence]
    train = [
        c
        for c in read_cameras(cap / "cameras.parquet")
        if c.split == "train" and (cameras is None or c.camera_id in cameras)
    ]
    keypoints = keypoints_by_camera(
        read_table(workspace / "keypoints" / sequence / "keypoints.parquet", KEYPOINTS), info.num_frames
    )
    keypoints = {c.camera_id: keypoints[c.camera_id] for c in train if c.camera_id in keypoints}
    views = _subset(load_views(cap, workspace / "frames", sequence, "train"), [c.camera_id for c in train])
    settings = RefineConfig()
    evidence = evidence_from_views(views, settings.render_size)
    fit_cfg = FitConfig(face_shape_columns=face_shape_columns(head, "auto", detector))
    truth = load_ground_truth_params(cap, sequence)
    rows = []
    for mode in modes:
        result = fit_sequence(keypoints, train, head, hand, fit_cfg, evidence, mode, settings)
        errors = tracking_errors(result.params, truth, head, hand)
        row = {"mode": mode, **{k: round(v, 2) for k, v in errors.items()}, "views": len(train)}
        if result.refinement is not None:
            iou = result.refinement.silhouette_iou
            row.update(
                {
                    f"iou_{p}_{when}": round(float(np.mean(list(iou[when][p].values()))), 3)
                    for when in ("before", "after")
                    for p in ("face", "hand")
                    if iou[when][p]
                }
            )
            row["s_per_frame_per_view"] = round(result.refinement.seconds / info.num_frames / len(train), 3)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True, help="a subject's folder under paths.outputs")
    parser.add_argument("--sequence", default="train")
    parser.add_argument("--modes", nargs="+", default=list(REFINE_MODES), choices=REFINE_MODES)
    parser.add_argument("--cameras", nargs="+", default=None, help="train cameras to use (default: all)")
    parser.add_argument("--detector", default="mediapipe", help="the detector the keypoints came from")
    parser.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    rows = measure(args.workspace, args.sequence, args.modes, args.cameras, args.detector)
    print(format_table(list(rows[0]), [[str(r.get(k, "-")) for k in rows[0]] for r in rows]))
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "bench_refine.json").write_text(
        json.dumps(
            {
                "commit": commit(),
                "machine": cpu_name(),
                "cores": os.cpu_count(),
                "load": os.getloadavg(),
                "workspace": str(args.workspace),
                "sequence": args.sequence,
                "cameras": args.cameras,
                "settings": asdict(RefineConfig()),
                "rows": rows,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
