"""The report's sections on the tracking: the fit's errors, the fitted, true and refined outlines over a crop, and
the training motion as the training stages refined it."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from avatar.artifacts import (
    TRAIN_SEQUENCE,
    load_params,
    load_views,
    read_params,
)
from avatar.fitting.refine import tracking_outlines
from avatar.render.rig_figure import SPLIT_NAMES
from avatar.templates import TemplateModel
from avatar.training.frame_params import parameter_movement
from data_schemas import web_escape as esc
from data_schemas.cameras import Camera
from data_schemas.frames import rgb_path
from data_schemas.images import read_png
from pipeline.stage import StageContext
from pipeline.summary import format_value
from reporting.html import base64_file, html_table, image_png, png_image

#: the outline figures are drawn at least this many pixels across: a smaller crop is upscaled first, so that the
#: one-pixel outlines stay thin and sharp
OUTLINE_MIN_PX = 256


#: the outline colours (RGB) of the fitted, the true and the refined-in-training meshes
FITTED_RGB, TRUE_RGB, REFINED_RGB = (255, 64, 64), (64, 160, 255), (64, 255, 64)


def outlines_image(
    image: np.ndarray,
    K: np.ndarray,
    world_to_cam: np.ndarray,
    param_sets: Sequence[Mapping[str, np.ndarray]],
    frame: int,
    meshes: tuple[TemplateModel, TemplateModel, bool],
    colours: Sequence[tuple[int, int, int]],
) -> np.ndarray:
    """:func:`tracking_outlines` of ``param_sets`` over ``image`` (S, S, 3) uint8 (intrinsics ``K``, pixel centres
    at integers; extrinsics ``world_to_cam``), upscaled to at least :data:`OUTLINE_MIN_PX` pixels.
    ``meshes``: (head, hand, with_hand)."""
    scale = max(1, math.ceil(OUTLINE_MIN_PX / image.shape[0]))
    K = np.asarray(K, np.float64)
    if scale > 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        up = np.array([[scale, 0.0, (scale - 1) / 2], [0.0, scale, (scale - 1) / 2], [0.0, 0.0, 1.0]])
        K = up @ K
    head, hand, with_hand = meshes
    return tracking_outlines(
        image,
        torch.from_numpy(K),
        torch.tensor(np.asarray(world_to_cam, np.float64)),
        param_sets,
        frame,
        head,
        hand,
        with_hand,
        colours,
    )


def outlines_section(
    frames_dir: Path,
    frames_index: Mapping[str, Any],
    camera: Camera,
    shown: tuple[str, int, str],
    fitted: Mapping[str, np.ndarray],
    truth: Mapping[str, np.ndarray] | None,
    meshes: tuple[TemplateModel, TemplateModel, bool],
    source: str,
) -> str:
    """The fitted meshes' outlines (red) over ``camera``'s crop (the frames stage's, ``frames_index``: its rows)
    of ``shown`` = (sequence, frame, why that frame) and, where the capture has ground truth (``truth``), the true
    meshes' (blue) under them. ``meshes``: (head, hand, with_hand); ``source``: fit_report.json's, where the
    parameters came from."""
    (seq, frame, why), camera_id = shown, camera.camera_id
    rows = [
        i
        for i in range(len(frames_index["frame"]))
        if frames_index["sequence"][i] == seq
        and frames_index["camera_id"][i] == camera_id
        and int(frames_index["frame"][i]) == frame
    ]
    if not rows:
        return f"<p>No crop of camera {esc.text(camera_id)} in frame {frame} of '{esc.text(seq)}' to draw on.</p>"
    image = read_png(rgb_path(frames_dir, seq, camera_id, frame), 3)
    K = np.asarray(frames_index["K"][rows[0]], np.float64).reshape(3, 3)
    sets, colours = ([truth, fitted], [TRUE_RGB, FITTED_RGB]) if truth is not None else ([fitted], [FITTED_RGB])
    figure = outlines_image(image, K, camera.world_to_cam, sets, frame, meshes, colours)
    caption = (
        f"Sequence '{seq}', frame {frame} ({why}), {SPLIT_NAMES.get(camera.split, 'camera')} {camera_id}: the fitted "
        "meshes' outlines (red)"
    )
    if truth is not None:
        caption += " over the true meshes' outlines (blue, the capture's ground truth)"
        if source == "ground_truth":
            caption += "; fit.source=ground_truth, so the two coincide"
    return (
        f"<figure>{png_image('fitted mesh outlines', image_png(figure))}"
        f"<figcaption>{esc.text(caption)}.</figcaption></figure>"
    )


def fit_section(fit_dir: Path) -> str:
    """Where the FLAME/MANO parameters came from and, per sequence, how well they fit."""
    report = json.loads((fit_dir / "fit_report.json").read_text())
    source = report["source"]
    intro = {
        "fitted": "fitted to the keypoints of the train views",
        "ground_truth": "the synthetic capture's own parameters (the avatar is measured apart from fitting error)",
        "provided": "the dataset's own fit",
    }.get(source, source)
    refine = report.get("refine", "none")
    rows, moves, figures = [], [], []
    for seq, entry in report["sequences"].items():
        stages = (
            [(seq, entry)]
            if "keypoint_fit" not in entry
            else [(f"{seq} (keypoint fit)", entry["keypoint_fit"]), (f"{seq} (refined: {refine})", entry)]
        )
        for name, values in stages:
            reproj = values.get("reprojection_px", {})
            weak = values.get("weak_frames", {})
            rows.append(
                (
                    name,
                    *(
                        format_value(values[k]) if k in values else "-"
                        for k in ("mpjpe_hand_mm", "mpjpe_face_mm", "vertex_error_hand_mm", "vertex_error_face_mm")
                    ),
                    *(format_value(reproj[p]) if p in reproj else "-" for p in ("hand", "face")),
                    "; ".join(f"{p}: {v}" for p, v in weak.items() if v) or "-",
                )
            )
        if "refinement" in entry:
            moves.append((seq, *refinement_cells(entry["refinement"])))
            figure = fit_dir / seq / "refinement.png"
            if figure.is_file():
                figures.append(
                    "<figure>"
                    + png_image(f"{seq}: keypoint fit and refined meshes", base64_file(figure))
                    + f"<figcaption>{esc.text(seq)}: keypoint fit (red) and refined (green) mesh outlines, the "
                    "frame that moved most</figcaption></figure>"
                )
    table = html_table(
        (
            "sequence",
            "hand MPJPE mm",
            "face landmarks mm",
            "hand vertices mm",
            "face vertices mm",
            "hand reprojection px",
            "face reprojection px",
            "weakly constrained frames",
        ),
        rows,
    )
    text = f"<p>Parameters: {esc.text(intro)}. Errors against ground truth where the capture has it.</p>{table}"
    if moves:
        text += (
            f"<p>The keypoint fit refined by the train views' {esc.text(refine)} (never the held-out "
            f"camera): silhouette IoU of the parts (mean over views, keypoint fit → refined) and how far "
            f"each part moved per frame (mean vertex displacement; change of global rotation).</p>"
            + html_table(
                (
                    "sequence",
                    "face IoU",
                    "hand IoU",
                    "face moved mm (mean / max)",
                    "hand moved mm (mean / max)",
                    "face rotated deg (max)",
                    "hand rotated deg (max)",
                ),
                moves,
            )
            + "".join(figures)
        )
    return text


def refinement_cells(refinement: dict) -> list[str]:
    """The report's cells of one sequence's image refinement (fit_report.json's ``refinement``)."""
    iou = refinement["silhouette_iou"]

    def mean_iou(stage: str, part: str) -> str:
        values = list(iou[stage].get(part, {}).values())
        return format_value(float(np.mean(values))) if values else "-"

    cells = [f"{mean_iou('keypoint_fit', p)} → {mean_iou('refined', p)}" for p in ("face", "hand")]
    for p in ("face", "hand"):
        moved = refinement["moved_mm"].get(p)
        cells.append(f"{format_value(float(np.mean(moved)))} / {format_value(float(np.max(moved)))}" if moved else "-")
    cells += [
        format_value(float(np.max(refinement["rotated_deg"][p]))) if refinement["rotated_deg"].get(p) else "-"
        for p in ("face", "hand")
    ]
    return cells


def trained_tracking_section(
    ctx: StageContext, manifests: dict[str, dict], head: TemplateModel, hand: TemplateModel
) -> str:
    """How training refined the train motion's parameters (``refine_params``): per frame, how far each part of the
    method's ``dynamic/params.parquet`` lies from the fit's (mean vertex displacement, change of global rotation),
    and the fitted (red) against the refined (green) meshes over the first training view, in the frame that moved
    most. Empty for runs that wrote no params.parquet."""
    trained = ctx.input_dir("dynamic") / "params.parquet"
    if not trained.is_file():
        return ""
    refined = [name for name in ("warmup", "dynamic") if manifests[name]["metrics"].get("params_refined")]
    if not refined:
        return (
            "<p>Training used these parameters as they are (stage.warmup.refine_params and "
            "stage.dynamic.refine_params off; <code>auto</code> is off with ground-truth tracking).</p>"
        )
    fitted = load_params(ctx.input_dir("fit"), TRAIN_SEQUENCE)
    after = read_params(trained)
    moved = parameter_movement(fitted, after, head, hand)
    rows = [
        (
            t,
            *(
                format_value(float(moved[kind][part][t]))
                for part in ("face", "hand")
                for kind in ("moved_mm", "rotated_deg")
            ),
        )
        for t in range(len(moved["moved_mm"]["face"]))
    ]
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), TRAIN_SEQUENCE, "train")
    frame = int(np.argmax(moved["moved_mm"]["face"] + moved["moved_mm"]["hand"]))
    figure = outlines_image(
        views.images[frame, 0].numpy(),
        views.K[0].numpy(),
        views.world_to_cam[0].numpy(),
        [fitted, after],
        frame,
        (head, hand, True),
        [FITTED_RGB, REFINED_RGB],
    )
    return (
        f"<p>Training refined the train motion's parameters with the avatar ({' and '.join(refined)}; "
        f"GaussianAvatars' fine-tuning of the tracking, against the train views only; the frames withheld for "
        f"validation and the held-out motion stay as fitted). Per frame, how far each part moved from the fit "
        f"(mean vertex displacement, mm; change of global rotation, degrees):</p>"
        + html_table(("frame", "face mm", "face deg", "hand mm", "hand deg"), rows)
        + "<figure>"
        + png_image(f"fitted and refined meshes, train frame {frame}", image_png(figure))
        + f"<figcaption>Train frame {frame}, camera "
        f"{esc.text(views.camera_ids[0])}: fitted (red) and refined in training (green) mesh outlines"
        f"</figcaption></figure>"
    )
