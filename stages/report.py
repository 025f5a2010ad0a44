"""Stage ``report``: one self-contained HTML page about a subject's run."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from avatar.artifacts import (
    load_ground_truth_params,
    load_params,
)
from avatar.artifacts.dependencies import TEMPLATE_KEYS
from avatar.artifacts.motion import templates
from avatar.representations import representation_class
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex
from data_schemas.frames import FRAMES_INDEX
from data_schemas.tables import read_table
from data_schemas.writes import write_bytes
from pipeline.manifest import MANIFEST_NAME
from pipeline.stage import StageContext, stage
from reporting.capture import (
    cameras_table,
    contact_sheet_section,
    contact_summary,
    intro,
    posed_meshes,
    rig_section,
    showcase_frame,
    stages_table,
)
from reporting.comparison import comparison_section
from reporting.evaluation import held_out_tracking_section, metrics_section, renders_section
from reporting.fit import fit_section, outlines_section, trained_tracking_section
from reporting.html import contact_sheet, page, png_image
from reporting.reenact import reenact_section, viewer_section
from reporting.scene import pbd_section, scene_section
from reporting.training import dynamic_summary, loss_curve, validation_section

UPSTREAM = (
    "capture",
    "frames",
    "fit",
    "scene",
    "pbd",
    "warmup",
    "dynamic",
    "evaluate",
    "compare",
    "reenact",
    "viewer",
)


@dataclass
class ReportConfig:
    """Types of ``stage.report`` (values in conf/stage/report.yaml)."""

    thumbnail_px: int


@stage(
    "report",
    inputs=UPSTREAM,
    config_keys=("quality.name", "method.name", "method.label", "stage.report", *TEMPLATE_KEYS),
    outputs=("report.html",),
    # 20: the held-out motion tracked by the avatar; 19: what validation withheld and what the model trained on;
    # 18: the rig, the fitted (and true) outlines over a training crop; the contact sheet in rows
    version="20",
    config_schema=ReportConfig,
    per_method=True,
    reads_manifests=True,
)  # its Stages table shows timings
def report(ctx: StageContext) -> None:
    """Write report.html: what was captured and modeled, per-stage timings and metrics, the methods side by
    side, a contact sheet."""
    cap_dir, frames_dir = ctx.input_dir("capture"), ctx.input_dir("frames")
    index = CaptureIndex.read(cap_dir)
    cameras = read_cameras(cap_dir / "cameras.parquet")
    frames_index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    manifests = {name: json.loads((ctx.input_dir(name) / MANIFEST_NAME).read_text()) for name in UPSTREAM}
    seq = "train" if "train" in index.sequences else next(iter(index.sequences))
    frame, why = showcase_frame(cap_dir, seq, index)
    sheet = contact_sheet(
        frames_dir, seq, [c.camera_id for c in cameras], frame, int(ctx.cfg.stage.report.thumbnail_px)
    )
    head, hand = templates(ctx.cfg.model)
    fit_dir = ctx.input_dir("fit")
    fit_info = json.loads((fit_dir / "fit_report.json").read_text())
    with_hand = bool(fit_info["sequences"].get(seq, {}).get("hand_fitted", True))  # no placeholder hand drawn
    fitted = load_params(fit_dir, seq)
    truth = load_ground_truth_params(cap_dir, seq) if index.sequences[seq].has_ground_truth else None
    # the first training camera, as load_views orders them (any camera where none trains)
    first_train = min((c for c in cameras if c.split == "train"), key=lambda c: c.camera_id, default=cameras[0])
    hand_share = float(np.mean(frames_index["hand_visible"]))
    label = str(ctx.cfg.method.label)
    sections = [
        intro(
            ctx.subject, str(ctx.method), label, str(ctx.cfg.quality.name), index.dataset, index.sequences, len(cameras)
        ),
        "<h2>What the scene contains</h2>",
        f"<p>The hand is visible in {100 * hand_share:.0f}% of the crops.</p>",
        contact_summary(cap_dir, index),
        "<h2>What was modelled, and why</h2>",
        scene_section(ctx.input_dir("scene"), manifests),
        "<h2>Stages</h2>",
        stages_table(manifests),
        "<h2>Cameras</h2>",
        rig_section(cameras, posed_meshes(fitted, frame, head, hand, with_hand), seq, frame),
        cameras_table(cameras),
        "<h2>Fitted meshes</h2>",
        fit_section(fit_dir),
        outlines_section(
            frames_dir,
            frames_index,
            first_train,
            (seq, frame, why),
            fitted,
            truth,
            (head, hand, with_hand),
            str(fit_info["source"]),
        ),
        trained_tracking_section(ctx, manifests, head, hand),
        "<h2>Contact deformation</h2>",
        pbd_section(ctx.input_dir("pbd")),
        "<h2>Image quality (held-out camera and held-out motion)</h2>",
        metrics_section(ctx.input_dir("evaluate")),
        held_out_tracking_section(
            ctx,
            manifests["evaluate"],
            head,
            hand,
            lambda s: load_ground_truth_params(cap_dir, s) if index.sequences[s].has_ground_truth else None,
        ),
        "<h2>Reenactment</h2>",
        reenact_section(ctx.input_dir("reenact")),
        "<h2>In 3D, in the browser</h2>",
        viewer_section(ctx.input_dir("viewer")),
        "<h2>Methods side by side</h2>",
        comparison_section(ctx.input_dir("compare")),
        "<h2>Training</h2>",
        "<p>Stage one, the warm-up, then stage two (for InteractAvatar and its ablations the hand MLPs H, the "
        "interaction MLPs I and PointNet++; for the baselines the same Gaussians trained on): "
        + dynamic_summary(manifests["dynamic"])
        + "</p>",
        *(
            png_image(f"{name} loss curve", loss_curve(ctx.input_dir(name), *curve))
            for name, curve in representation_class(str(ctx.cfg.method.representation)).train_logs.items()
        ),
        validation_section(ctx.input_dir("warmup"), ctx.input_dir("dynamic")),
        contact_sheet_section(seq, frame, why, sheet, cameras),
        renders_section(label, ctx.input_dir("evaluate") / "grids"),
    ]
    write_bytes(ctx.out_dir / "report.html", page(sections).encode(), "report")
