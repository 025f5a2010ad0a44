"""The report's sections on image quality: the metrics per split and region, the held-out motion tracked by the
avatar, the renders."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from avatar.artifacts import (
    load_params,
    load_views,
    read_params,
)
from avatar.templates import TemplateModel
from avatar.training.frame_params import parameter_movement
from data_schemas import web_escape as esc
from data_schemas.metrics import METRICS, REGIONS, SPLITS
from data_schemas.tables import read_table
from pipeline.stage import StageContext
from pipeline.summary import format_value
from reporting.fit import FITTED_RGB, REFINED_RGB, TRUE_RGB, outlines_image
from reporting.html import base64_file, html_table, image_png, png_image


def renders_section(label: str, grids: Path) -> str:
    """The evaluate stage's image grids per split (ground truth, the method ``label``, its error)."""
    return f"<h2>Renders: ground truth | {esc.text(label)} | its error x4</h2>" + "".join(
        f"<h3>{esc.text(s)}</h3>" + png_image(s, base64_file(grids / f"{s}.png"))
        for s in SPLITS
        if (grids / f"{s}.png").is_file()
    )


def held_out_tracking_section(
    ctx: StageContext, evaluate: dict, head: TemplateModel, hand: TemplateModel, truth_of: Callable[[str], Any]
) -> str:
    """How the avatar tracked the held-out motion (``stage.evaluate.test_tracking=avatar``): the cameras that tuned
    and scored it, its PSNR under both protocols on the scoring cameras, the 3D errors before and after (synthetic),
    per frame how far each part moved from the fit, and the fitted (red), avatar-tracked (green) and, where known,
    true (blue) meshes over the first tuning camera in the frame that moved most. Empty for the tracker protocol."""
    m = evaluate["metrics"]
    sequence_dirs = sorted(p for p in (ctx.input_dir("evaluate") / "tracking").glob("*") if p.is_dir())
    if not sequence_dirs:
        return ""
    seq = sequence_dirs[0].name
    fitted, after = load_params(ctx.input_dir("fit"), seq), read_params(sequence_dirs[0] / "params.parquet")
    moved = parameter_movement(fitted, after, head, hand)
    rows = [
        (t, *(format_value(float(moved[k][part][t])) for part in ("face", "hand") for k in ("moved_mm", "rotated_deg")))
        for t in range(len(moved["moved_mm"]["face"]))
    ]
    errors = [
        (label, format_value(m[f"tracking_before_{key}"]), format_value(m[f"tracking_after_{key}"]))
        for key, label in (
            ("mpjpe_hand_mm", "hand MPJPE"),
            ("mpjpe_face_mm", "face landmarks"),
            ("vertex_error_face_mm", "face vertices"),
        )
        if f"tracking_before_{key}" in m
    ]
    tuning = str(m["tracking_tuning_cameras"]).split(",")
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), seq, "train").cameras(tuning[:1])
    frame = int(np.argmax(moved["moved_mm"]["face"] + moved["moved_mm"]["hand"]))
    truth = truth_of(seq)
    sets, colours = [fitted, after], [FITTED_RGB, REFINED_RGB]
    if truth is not None:
        sets, colours = [*sets, truth], [*colours, TRUE_RGB]
    figure = outlines_image(
        views.images[frame, 0].numpy(),
        views.K[0].numpy(),
        views.world_to_cam[0].numpy(),
        sets,
        frame,
        (head, hand, True),
        colours,
    )
    return (
        f"<h3>The held-out motion tracked by the avatar</h3><p>Each frame of '{esc.text(seq)}' was refined with the "
        f"trained model frozen on the training cameras {esc.text(', '.join(tuning))} and scored on the others "
        f"({esc.text(str(m['tracking_scoring_cameras']).replace(',', ', '))}; never the held-out camera): full-image "
        f"PSNR {format_value(m['self_reenact_scoring_psnr'])} dB posed as the fit tracked it, "
        f"{format_value(m['self_reenact_tracked_psnr'])} dB as the avatar tracked it (split self_reenact_tracked), "
        f"in {format_value(m['tracking_seconds'])} s.</p>"
        + (html_table(("3D error (mm)", "fit", "tracked by the avatar"), errors) if errors else "")
        + "<p>Per frame, how far each part moved from the fit (mean vertex displacement, mm; change of global "
        "rotation, degrees):</p>"
        + html_table(("frame", "face mm", "face deg", "hand mm", "hand deg"), rows)
        + "<figure>"
        + png_image(f"fitted and avatar-tracked meshes, {seq} frame {frame}", image_png(figure))
        + f"<figcaption>Frame {frame} of '{esc.text(seq)}', camera {esc.text(tuning[0])}: fitted (red), tracked by "
        f"the avatar (green){' and true (blue)' if truth is not None else ''} mesh outlines</figcaption></figure>"
    )


def metrics_section(evaluate_dir: Path) -> str:
    """Mean PSNR / SSIM / LPIPS per method, split and region (NaN regions skipped)."""
    t = read_table(evaluate_dir / "metrics.parquet", METRICS)
    rows = []
    for method in sorted(set(t["method"])):
        for split in SPLITS:
            for region in REGIONS:
                sel = [
                    i
                    for i in range(len(t["frame"]))
                    if t["method"][i] == method and t["split"][i] == split and t["region"][i] == region
                ]
                vals = {m: np.asarray(t[m])[sel] for m in ("psnr", "ssim", "lpips")}
                defined = np.isfinite(vals["ssim"]) | np.isfinite(vals["psnr"])
                if not defined.any():
                    continue
                rows.append(
                    (
                        method,
                        split,
                        region,
                        int(defined.sum()),
                        *(f"{np.nanmean(np.where(np.isinf(v), np.nan, v)):.4g}" for v in vals.values()),
                    )
                )
    return html_table(("method", "split", "region", "images", "PSNR dB", "SSIM", "LPIPS"), rows)
