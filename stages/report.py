"""Stage ``report``: one self-contained HTML page about a subject's run."""

from __future__ import annotations

import base64
import io
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from avatar.artifacts import (
    TRAIN_SEQUENCE,
    contact_frames,
    contact_source,
    load_ground_truth_params,
    load_params,
    load_views,
    read_params,
)
from avatar.artifacts.dependencies import TEMPLATE_KEYS
from avatar.artifacts.motion import templates
from avatar.fitting.refine import tracking_outlines
from avatar.posing import posed_keypoints
from avatar.render.rig_figure import SPLIT_NAMES, rig_figure
from avatar.representations import representation_class
from avatar.templates import TemplateModel
from avatar.training.frame_params import parameter_movement
from data_schemas import web_escape as esc
from data_schemas.cameras import Camera, read_cameras
from data_schemas.capture import CaptureIndex, SequenceInfo
from data_schemas.curve import CURVE
from data_schemas.frames import FRAMES_INDEX, rgb_path
from data_schemas.images import read_png
from data_schemas.metrics import COMPARISON, METRICS, REGIONS, SPLITS
from data_schemas.tables import TableSchema, read_table
from data_schemas.writes import write_bytes
from pipeline.manifest import MANIFEST_NAME
from pipeline.stage import StageContext, stage
from pipeline.summary import format_value

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
    frame, why = _showcase_frame(cap_dir, seq, index)
    sheet = _contact_sheet(
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
        _intro(
            ctx.subject, str(ctx.method), label, str(ctx.cfg.quality.name), index.dataset, index.sequences, len(cameras)
        ),
        "<h2>What the scene contains</h2>",
        f"<p>The hand is visible in {100 * hand_share:.0f}% of the crops.</p>",
        _contact_summary(cap_dir, index),
        "<h2>What was modelled, and why</h2>",
        _scene_section(ctx.input_dir("scene"), manifests),
        "<h2>Stages</h2>",
        _stages_table(manifests),
        "<h2>Cameras</h2>",
        _rig_section(cameras, _posed_meshes(fitted, frame, head, hand, with_hand), seq, frame),
        _cameras_table(cameras),
        "<h2>Fitted meshes</h2>",
        _fit_section(fit_dir),
        _outlines_section(
            frames_dir,
            frames_index,
            first_train,
            (seq, frame, why),
            fitted,
            truth,
            (head, hand, with_hand),
            str(fit_info["source"]),
        ),
        _trained_tracking_section(ctx, manifests, head, hand),
        "<h2>Contact deformation</h2>",
        _pbd_section(ctx.input_dir("pbd")),
        "<h2>Image quality (held-out camera and held-out motion)</h2>",
        _metrics_section(ctx.input_dir("evaluate")),
        _test_tracking_section(
            ctx,
            manifests["evaluate"],
            head,
            hand,
            lambda s: load_ground_truth_params(cap_dir, s) if index.sequences[s].has_ground_truth else None,
        ),
        "<h2>Reenactment</h2>",
        _reenact_section(ctx.input_dir("reenact")),
        "<h2>In 3D, in the browser</h2>",
        _viewer_section(ctx.input_dir("viewer")),
        "<h2>Methods side by side</h2>",
        _comparison_section(ctx.input_dir("compare")),
        "<h2>Training</h2>",
        "<p>Stage one, the warm-up, then stage two (for InteractAvatar and its ablations the hand MLPs H, the "
        "interaction MLPs I and PointNet++; for the baselines the same Gaussians trained on): "
        + _dynamic_summary(manifests["dynamic"])
        + "</p>",
        *(
            _png_image(f"{name} loss curve", _loss_curve(ctx.input_dir(name), *curve))
            for name, curve in representation_class(str(ctx.cfg.method.representation)).train_logs.items()
        ),
        _validation_section(ctx.input_dir("warmup"), ctx.input_dir("dynamic")),
        _contact_sheet_section(seq, frame, why, sheet, cameras),
        _renders_section(label, ctx.input_dir("evaluate") / "grids"),
    ]
    write_bytes(ctx.out_dir / "report.html", _page(sections).encode(), "report")


def _page(sections: list[str]) -> str:
    """The report's HTML document around its ``sections`` (HTML, every name in them escaped)."""
    return (
        "<!doctype html><meta charset='utf-8'><title>InteractAvatar report</title>"
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}"
        "img,video{max-width:100%;height:auto}figure{margin:1em 0}</style>\n" + "\n".join(sections)
    )


def _intro(
    subject: str,
    method: str,
    label: str,
    quality: str,
    dataset: str,
    sequences: dict[str, SequenceInfo],
    num_cameras: int,
) -> str:
    """The title and the paragraph on what was run: subject, method, dataset, preset, cameras, sequences."""
    listed = ", ".join(f"{k} ({v.num_frames} frames, {v.width}x{v.height})" for k, v in sequences.items())
    return (
        f"<h1>InteractAvatar report: {esc.text(subject)}</h1>"
        f"<p>method <b>{esc.text(label)}</b> ({esc.text(method)}), dataset <b>{esc.text(dataset)}</b>, "
        f"quality preset <b>{esc.text(quality)}</b>, {num_cameras} cameras, sequences: {esc.text(listed)}</p>"
    )


def _stages_table(manifests: dict[str, dict]) -> str:
    """Per upstream stage: wall time, peak memory, its metrics and when it was written (from its manifest)."""
    return _table(
        ("stage", "wall s", "peak MB", "metrics", "written"),
        [
            (
                n,
                f"{m['timings']['wall_s']:.2f}",
                f"{m['peak_memory_mb']:.0f}",
                ", ".join(f"{k}={format_value(v)}" for k, v in sorted(m["metrics"].items())),
                m["created"],
            )
            for n, m in manifests.items()
        ],
    )


def _cameras_table(cameras: list[Camera]) -> str:
    """Per capture camera: id, split, size, focal length and position."""
    return _table(
        ("camera", "split", "size", "fx", "position (m)"),
        [
            (
                c.camera_id,
                c.split,
                f"{c.width}x{c.height}",
                f"{c.K[0, 0]:.1f}",
                np.array2string(c.cam_to_world[:3, 3], precision=3),
            )
            for c in cameras
        ],
    )


def _contact_sheet_section(seq: str, frame: int, why: str, sheet_png: str, cameras: Sequence[Camera] = ()) -> str:
    """Every camera's crop of one frame in rows (``sheet_png``: base64 PNG of :func:`_contact_sheet`), with what
    it shows and, given the ``cameras`` in the sheet's order, which tile is which."""
    order = ", ".join(f"{c.camera_id} ({SPLIT_NAMES.get(c.split, c.split)})" for c in cameras)
    caption = f"<figcaption>Row by row: {esc.text(order)}.</figcaption>" if order else ""
    return (
        f"<h2>All views, sequence '{esc.text(seq)}', frame {frame} ({esc.text(why)})</h2>"
        f"<figure>{_png_image('contact sheet', sheet_png)}{caption}</figure>"
    )


def _renders_section(label: str, grids: Path) -> str:
    """The evaluate stage's image grids per split (ground truth, the method ``label``, its error)."""
    return f"<h2>Renders: ground truth | {esc.text(label)} | its error x4</h2>" + "".join(
        f"<h3>{esc.text(s)}</h3>" + _png_image(s, _base64_file(grids / f"{s}.png"))
        for s in SPLITS
        if (grids / f"{s}.png").is_file()
    )


def _scene_section(scene_dir: Path, manifests: dict[str, dict]) -> str:
    """The scene stage's decisions with their reasons, and the work they left out."""
    info = json.loads((scene_dir / "scene.json").read_text())
    rows = [
        (name.removeprefix("model_"), "yes" if info[name] else "no", info["why"][name])
        for name in ("model_hand", "model_pbd", "model_interaction")
    ]
    dynamic = manifests["dynamic"]["metrics"]
    work = (
        f"PBD simulated {manifests['pbd']['metrics'].get('simulated_frames', 0)} frames; the interaction MLPs "
        f"ran {dynamic.get('interaction_mlp_evaluations', 0)} Gaussian evaluations in training; "
        f"{len(info['deforming_triangles'])} of {info['face_triangles']} face triangles lie within d_max = "
        f"{info['d_max_m'] * 100:g} cm of the hand in some training contact frame (the only ones the interaction "
        f"module and PBD can reach). Decided on the '{info['decided_on']}' sequence; stage.scene.* overrides."
    )
    left_out = []
    if not info["model_hand"]:
        per_triangle = int(manifests["warmup"]["config"]["quality.gaussians_per_triangle"])
        left_out.append(
            f"{info['hand_triangles']} MANO triangles without Gaussians (about "
            f"{info['hand_triangles'] * per_triangle} Gaussians not created at this preset) "
            "and no hand MLPs"
        )
    if not info["model_pbd"]:
        left_out.append("no contact simulated in any frame")
    if not info["model_interaction"]:
        left_out.append("no interaction MLPs and no PointNet++")
    saved = (
        (
            "Left out: " + "; ".join(left_out) + ". benchmarks/bench_scene.py measures the time this saves "
            "against modelling everything (docs/explanation/scene.md)."
        )
        if left_out
        else ""
    )
    return (
        _table(("modelled", "", "why"), rows)
        + f"<p>{esc.text(work)}</p>"
        + (f"<p>{esc.text(saved)}</p>" if saved else "")
        + _contact_draws_paragraph(manifests["dynamic"])
        + _withheld_paragraph(manifests["dynamic"])
        + _selection_paragraph(dynamic)
    )


def _contact_draws_paragraph(dynamic: dict) -> str:
    """How often stage two drew the contact frames (stage.dynamic.contact_fraction, capped by
    max_contact_emphasis); nothing for a manifest from before the cap or without contact frames."""
    p = dynamic["metrics"].get("contact_draw_probability")
    conf = dynamic["config"].get("stage.dynamic", {})
    if p is None or not dynamic["metrics"].get("contact_frames") or "contact_fraction" not in conf:
        return ""
    fraction = float(conf["contact_fraction"])
    text = f"Stage two drew a contact frame first with probability {p:.2f}, else any training frame"
    if p < fraction and "max_contact_emphasis" in conf:
        text += (
            f" (contact_fraction {fraction:g}, lowered so that no contact frame is drawn more than "
            f"{float(conf['max_contact_emphasis']):g} times as often as a frame without contact: with few contact "
            "frames the Gaussians would fit their tracking error)"
        )
    return f"<p>{esc.text(text)}.</p>"


def _withheld_paragraph(dynamic: dict) -> str:
    """What validation withheld and what the written model trained on (``validation_frames_withheld``,
    ``final_training_frames``); nothing for a manifest from before they were recorded."""
    metrics, conf = dynamic["metrics"], dynamic["config"].get("stage.dynamic", {})
    withheld, final = metrics.get("validation_frames_withheld"), metrics.get("final_training_frames")
    validation = conf.get("validation", {})
    if withheld is None or final is None or not int(validation.get("every", 0)):
        return ""
    if not withheld:
        text = (
            f"Nothing could be withheld for validation: with {final} training frames, at least "
            f"{validation.get('min_train_frames')} must stay to train on (stage.dynamic.validation.min_train_frames), "
            "so stage two trained on all of them and chose nothing"
        )
    elif metrics.get("retrained_on_all_frames"):
        text = (
            f"Validation withheld {withheld} of {final} training frames (fraction {validation.get('fraction')}) to "
            f"choose on; the model shown was then trained again on all {final} frames with what was chosen"
        )
    else:
        text = (
            f"Validation withheld {withheld} training frames (fraction {validation.get('fraction')}); the model shown "
            f"trained on the other {final} (stage.dynamic.validation.retrain=false)"
        )
    return f"<p>{esc.text(text)}.</p>"


def _selection_paragraph(dynamic: dict) -> str:
    """What stage two's selection kept (stage.dynamic.select), on the validation figures it rests on; nothing
    when it did not run."""
    if "selected_step" not in dynamic:
        return "<p>Stage two kept its last step and every module it built (stage.dynamic.select.enabled=false).</p>"
    step, final = int(dynamic["selected_step"]), int(dynamic["selection_final_step"])
    text = (
        f"Stage two kept step {step} of {final}"
        + (" (the warm-up's model: H and I at zero)" if step == 0 else "")
        + f": validation PSNR {dynamic['selection_selected_psnr']:.2f} dB against "
        f"{dynamic['selection_final_psnr']:.2f} dB at the last step, on training frames that neither stage "
        "trained on."
    )
    for module, name in (("hand_mlp", "the hand MLPs H"), ("interaction", "the interaction MLPs I")):
        without = dynamic.get(f"selection_psnr_without_{module}")
        if without is None:
            text += f" {name[0].upper()}{name[1:]}: not built."
            continue
        kept = bool(dynamic[f"kept_{module}"])
        if dynamic.get(f"selection_judged_{module}") is False:
            text += (
                f" {name[0].upper()}{name[1:]}: kept without being judged (none of the withheld frames has "
                "contact, which they model)."
            )
            continue
        text += (
            f" {name[0].upper()}{name[1:]}: {'kept' if kept else 'switched off'} (validation PSNR without them "
            f"{without:.2f} dB)."
        )
    if "restarts" in dynamic:
        text += (
            f" Best of {dynamic['restarts']} initialisations of stage two on validation (kept: number "
            f"{int(dynamic['selected_restart']) + 1}, seed {dynamic['selected_seed']})."
        )
    return f"<p>{esc.text(text)} Rule: docs/explanation/selection.md.</p>"


def _showcase_frame(cap_dir: Path, seq: str, index: CaptureIndex) -> tuple[int, str]:
    """First contact frame when ground truth says so, else the middle frame."""
    contact = contact_frames(cap_dir, seq, index.sequences[seq].num_frames)
    if contact.any():
        return int(np.flatnonzero(contact)[0]), "first frame with hand-face contact"
    return index.sequences[seq].num_frames // 2, "middle frame"


def _contact_summary(cap_dir: Path, index: CaptureIndex) -> str:
    """Per sequence with contact labels, how many frames have contact and where the labels come from."""
    return _contact_paragraph(
        {
            seq: (int(contact_frames(cap_dir, seq, info.num_frames).sum()), info.num_frames, source)
            for seq, info in index.sequences.items()
            if (source := contact_source(info)) is not None
        }
    )


def _contact_paragraph(counts: dict[str, tuple[int, int, str]]) -> str:
    """The paragraph of :func:`_contact_summary` from sequence -> (contact frames, frames, label source)."""
    parts = [f"{seq}: {n} of {total} frames with contact ({source})" for seq, (n, total, source) in counts.items()]
    return f"<p>{esc.text('; '.join(parts))}</p>" if parts else "<p>No contact labels in this capture.</p>"


def _posed_meshes(
    params: Mapping[str, np.ndarray], frame: int, head: TemplateModel, hand: TemplateModel, with_hand: bool
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Part -> ((V, 3) world vertices, (F, 3) triangles) of the face (and hand) that ``params`` pose at ``frame``."""
    posed = posed_keypoints({k: np.asarray(v)[frame : frame + 1] for k, v in params.items()}, head, hand)
    meshes = {"face": (np.asarray(posed["face_vertices"][0]), np.asarray(head.faces))}
    if with_hand:
        meshes["hand"] = (np.asarray(posed["hand_vertices"][0]), np.asarray(hand.faces))
    return meshes


def _rig_section(cameras: list[Camera], meshes: dict[str, tuple[np.ndarray, np.ndarray]], seq: str, frame: int) -> str:
    """The rig from above and from the front: the cameras (train and held-out in two colours, with their ids)
    around the fitted meshes of ``seq``'s ``frame`` (``meshes``: :func:`_posed_meshes`)."""
    caption = (
        f"The cameras around the fitted meshes (sequence '{seq}', frame {frame}), in world space: blue the "
        "training cameras, orange the held-out one(s); each frustum drawn to a quarter of its distance from the "
        "subject, an id left out where it would cover another."
    )
    return (
        f"<figure>{_png_image('the capture rig', _figure_png(rig_figure(cameras, meshes)))}"
        f"<figcaption>{esc.text(caption)}</figcaption></figure>"
    )


#: the outline figures are drawn at least this many pixels across: a smaller crop is upscaled first, so that the
#: one-pixel outlines stay thin and sharp
OUTLINE_MIN_PX = 256
#: the outline colours (RGB) of the fitted, the true and the refined-in-training meshes
FITTED_RGB, TRUE_RGB, REFINED_RGB = (255, 64, 64), (64, 160, 255), (64, 255, 64)


def _outlines_image(
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


def _outlines_section(
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
    figure = _outlines_image(image, K, camera.world_to_cam, sets, frame, meshes, colours)
    caption = (
        f"Sequence '{seq}', frame {frame} ({why}), {SPLIT_NAMES.get(camera.split, 'camera')} {camera_id}: the fitted "
        "meshes' outlines (red)"
    )
    if truth is not None:
        caption += " over the true meshes' outlines (blue, the capture's ground truth)"
        if source == "ground_truth":
            caption += "; fit.source=ground_truth, so the two coincide"
    return (
        f"<figure>{_png_image('fitted mesh outlines', _image_png(figure))}"
        f"<figcaption>{esc.text(caption)}.</figcaption></figure>"
    )


def _fit_section(fit_dir: Path) -> str:
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
            moves.append((seq, *_refinement_cells(entry["refinement"])))
            figure = fit_dir / seq / "refinement.png"
            if figure.is_file():
                figures.append(
                    "<figure>"
                    + _png_image(f"{seq}: keypoint fit and refined meshes", _base64_file(figure))
                    + f"<figcaption>{esc.text(seq)}: keypoint fit (red) and refined (green) mesh outlines, the "
                    "frame that moved most</figcaption></figure>"
                )
    table = _table(
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
            + _table(
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


def _refinement_cells(refinement: dict) -> list[str]:
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


def _trained_tracking_section(
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
    figure = _outlines_image(
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
        + _table(("frame", "face mm", "face deg", "hand mm", "hand deg"), rows)
        + "<figure>"
        + _png_image(f"fitted and refined meshes, train frame {frame}", _image_png(figure))
        + f"<figcaption>Train frame {frame}, camera "
        f"{esc.text(views.camera_ids[0])}: fitted (red) and refined in training (green) mesh outlines"
        f"</figcaption></figure>"
    )


def _test_tracking_section(
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
    figure = _outlines_image(
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
        + (_table(("3D error (mm)", "fit", "tracked by the avatar"), errors) if errors else "")
        + "<p>Per frame, how far each part moved from the fit (mean vertex displacement, mm; change of global "
        "rotation, degrees):</p>"
        + _table(("frame", "face mm", "face deg", "hand mm", "hand deg"), rows)
        + "<figure>"
        + _png_image(f"fitted and avatar-tracked meshes, {seq} frame {frame}", _image_png(figure))
        + f"<figcaption>Frame {frame} of '{esc.text(seq)}', camera {esc.text(tuning[0])}: fitted (red), tracked by "
        f"the avatar (green){' and true (blue)' if truth is not None else ''} mesh outlines</figcaption></figure>"
    )


def _pbd_section(pbd_dir: Path) -> str:
    """Where the face offsets came from and, per sequence, what was simulated and how close to the truth."""
    report = json.loads((pbd_dir / "pbd_report.json").read_text())
    rows = []
    for seq, entry in report["sequences"].items():
        frames = entry["frames"]
        simulated = [f for f in frames if f["simulated"]]
        errors = entry.get("ground_truth_error") or {}
        rows.append(
            (
                seq,
                len(frames),
                sum(f["near"] for f in frames),
                len(simulated),
                format_value(max((f["penetration_max_mm"] for f in simulated), default=0.0)),
                format_value(max(f["max_offset_mm"] for f in frames)),
                *(format_value(errors[k]) if k in errors else "-" for k in ("mean_mm", "zero_mean_mm")),
            )
        )
    table = _table(
        (
            "sequence",
            "frames",
            "hand near the face",
            "simulated",
            "residual penetration mm",
            "largest offset mm",
            "vertex error mm",
            "zero offsets mm",
        ),
        rows,
    )
    stiffness = f", stiffness from {report['stiffness']}" if "stiffness" in report else ""
    intro = f"Offsets: {report['source']}{stiffness} ({report['frame_convention']})"
    return (
        f"<p>{esc.text(intro)}; frames whose hand stays clear of the face are not simulated. Vertex errors "
        f"over the vertices that move in contact frames, against ground truth where the capture has it.</p>{table}"
    )


def _metrics_section(evaluate_dir: Path) -> str:
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
    return _table(("method", "split", "region", "images", "PSNR dB", "SSIM", "LPIPS"), rows)


def _reenact_section(reenact_dir: Path) -> str:
    """Who drove the avatar, the contact it made, the render speed, and the videos (playable in the page)."""
    info = json.loads((reenact_dir / "reenact_report.json").read_text())
    metrics = json.loads((reenact_dir / MANIFEST_NAME).read_text())["metrics"]
    simulated = [f for f in info["pbd"]["frames"] if f["simulated"]]
    worst = max((f["penetration_max_mm"] for f in simulated), default=0.0)
    text = (
        f"Driver: {info['driver']}, {info['frames']} frames, head-size ratio {info['head_scale']:.3f}; contact "
        + (
            f"simulated on {len(simulated)} frames (worst residual penetration {worst:.2f} mm)"
            if info["pbd"]["simulated"]
            else "not simulated (the method has no PBD)"
        )
        + f"; {metrics['frames_per_second']:.1f} frames per second at {metrics['image_size']} px "
        f"(model {metrics['model_ms_per_frame']:.0f} ms per frame, rasterizer "
        f"{metrics['render_ms_per_view']:.0f} ms per view)."
    )
    transfer = info.get("transfer", {"frames": []})
    touching = [f for f in transfer["frames"] if f["touching_points"]]
    if touching:
        text += (
            f" The driver's hand touches its face in {len(touching)} frames; placed to keep those touches "
            f"(reenact.placement={transfer['placement']}), {metrics['transfer_kept_fraction']:.0%} of the "
            f"touching points touch this face too, a mean {metrics['transfer_residual_mm']:.1f} mm from the "
            f"same surface points."
        )
    if info.get("sequence_note"):  # e.g. a capture without the held-out motion reenacts its training motion
        text += f" {info['sequence_note'][0].upper()}{info['sequence_note'][1:]}."
    truth = info["ground_truth"]
    text += (
        f" Beside the ground truth ({truth['sequence']}) on camera(s) {', '.join(truth['cameras'])}."
        if truth["cameras"]
        else f" No ground truth to show: {truth['note']}."
    )
    shown = []  # per view: reenacted | ground truth where the capture has it, else the reenactment alone
    for path in sorted((reenact_dir / "videos").glob("*.mp4")):
        if path.stem.endswith(("_gt", "_vs_gt")):
            continue
        paired = path.with_name(f"{path.stem}_vs_gt.mp4")
        shown.append((paired, f"{path.stem}: reenacted | ground truth") if paired.is_file() else (path, path.stem))
    videos = "".join(
        f"<figure style='display:inline-block;margin:4px'><video controls autoplay loop muted playsinline "
        f"src='data:video/mp4;base64,{_base64_file(path)}'></video><figcaption>{esc.text(caption)}</figcaption>"
        f"</figure>"
        for path, caption in shown
    )
    return f"<p>{esc.text(text)}</p>{videos}"


def _viewer_section(viewer_dir: Path) -> str:
    """Links to this method's browser viewer and to the other methods' (those written by now), with its sizes."""
    info = json.loads((viewer_dir / "viewer.json").read_text())
    others = sorted(p for p in viewer_dir.parent.parent.glob("*/viewer/index.html") if p.parent != viewer_dir)
    links = "".join(
        f" <a href='../../{esc.url_path(name, 'viewer', 'index.html')}'>{esc.text(name)}</a>"
        for name in (p.parent.parent.name for p in others)
    )
    built = (
        ""
        if info["page_built"]
        else f" The page is not built on this machine: run <code>{esc.text(info['build_command'])}</code>, then "
        "<code>interactavatar run.only=viewer</code>."
    )
    return (
        f"<p><a href='../viewer/index.html'>Open this avatar in the viewer</a>: orbit it, play its motions, step "
        f"through the frames beside the ground truth (from a server: <code>interactavatar-view "
        f"&lt;outputs&gt;/&lt;subject&gt;</code>).{built} {esc.text(info['gaussians'])} Gaussians, "
        f"{info['bytes_per_frame'] / 1e3:.0f} kB per frame, {info['mb_per_100_frames']:.1f} MB per 100 frames."
        + (f" The other methods' viewers:{links}." if links else "")
        + "</p>"
    )


def _comparison_section(compare_dir: Path) -> str:
    """The compare stage's tables, notes and image rows."""
    tables = json.loads((compare_dir / "tables.json").read_text())
    parts = []
    for table in tables["tables"]:
        parts += [f"<h3>{esc.text(table['title'])}</h3>", _table(tuple(table["headers"]), table["rows"])]
    parts.append("<ul>" + "".join(f"<li>{esc.text(note)}</li>" for note in tables["notes"]) + "</ul>")
    parts.append(_pareto_plot(compare_dir))
    for figure in sorted((compare_dir / "figures").glob("*.png")):
        parts.append(
            f"<h3>{esc.text(figure.stem.replace('_', ' '))}: ground truth, then each method</h3>"
            + _png_image(figure.stem, _base64_file(figure))
        )
    return "\n".join(parts)


def _dynamic_summary(manifest: dict) -> str:
    """One sentence on the dynamic stage's cost: steps, ms per step, interaction-MLP evaluations."""
    m = manifest["metrics"]
    if "interaction_steps" not in m:  # SplattingAvatar: no MLPs
        return esc.text(
            f"{m['steps']} steps at {m['ms_per_step']:.0f} ms each, {m.get('walked', 0)} triangle changes by walking"
        )
    return esc.text(
        f"{m['steps']} steps at {m['ms_per_step']:.0f} ms each; the interaction MLPs ran in "
        f"{m['interaction_steps']} steps on {m['interaction_mlp_evaluations']} Gaussians in all"
    )


def _loss_curve(train_dir: Path, schema: TableSchema, terms: tuple[str, ...]) -> str:
    """Base64 PNG of the loss ``terms`` of a stage's ``train_log.parquet`` against steps."""
    plt = _pyplot()
    log = read_table(train_dir / "train_log.parquet", schema)
    fig, ax = plt.subplots(figsize=(6, 3), dpi=100)
    for name in terms:
        ax.plot(log["step"], log[name], label=name)
    ax.set_xlabel("step")
    ax.set_yscale("log")
    ax.legend()
    return _figure_png(fig)


def _figure_png(fig) -> str:  # a matplotlib Figure
    """Base64 PNG of a matplotlib figure, closed afterwards."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _pyplot():  # the matplotlib.pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def pareto_front(cost: np.ndarray, quality: np.ndarray) -> np.ndarray:
    """(N,) bool: the points no other point beats, i.e. none is at most as costly and at least as good
    with one of the two strictly better. cost, quality: (N,)."""
    cost, quality = np.asarray(cost, float), np.asarray(quality, float)
    no_worse = (cost[None, :] <= cost[:, None]) & (quality[None, :] >= quality[:, None])
    better = (cost[None, :] < cost[:, None]) | (quality[None, :] > quality[:, None])
    return ~np.asarray((no_worse & better).any(axis=1))


def _pareto_plot(compare_dir: Path) -> str:
    """Held-out quality against training time, one point per method of the comparison, the Pareto front
    joined (novel view and self-reenactment, full images, all frames)."""
    table = read_table(compare_dir / "comparison.parquet", COMPARISON)
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), dpi=100)
    for ax, split in zip(axes, ("novel_view", "self_reenact")):
        rows = [
            i
            for i in range(len(table["method"]))
            if table["split"][i] == split and table["region"][i] == "full" and table["contact"][i] == "all"
        ]
        if not rows:
            continue
        cost = np.array([table["train_wall_s"][i] for i in rows], float)
        psnr = np.array([table["psnr"][i] for i in rows], float)
        front = pareto_front(cost, psnr)
        ax.scatter(cost, psnr, c=np.where(front, "tab:red", "tab:gray"))
        for i, c, q in zip(rows, cost, psnr):
            ax.annotate(str(table["label"][i]), (c, q), fontsize=8, xytext=(3, 3), textcoords="offset points")
        order = np.argsort(cost[front])
        ax.plot(cost[front][order], psnr[front][order], color="tab:red", linewidth=1)
        ax.set_xlabel("training wall time (s, warm-up + stage two)")
        ax.set_ylabel(f"{split.replace('_', ' ')} PSNR (dB)")
    png = _figure_png(fig)
    return (
        "<h3>Quality against training time (red: the Pareto front, methods no other beats on both)</h3>"
        + _png_image("quality against time", png)
    )


def _validation_section(warmup_dir: Path, dynamic_dir: Path) -> str:
    """The validation curves of the two training stages (stage.*.validation), one time axis: nothing when
    neither validated."""
    curves = {
        name: read_table(d / "curve.parquet", CURVE)
        for name, d in (("warm-up", warmup_dir), ("stage two", dynamic_dir))
        if (d / "curve.parquet").is_file()
    }
    curves = {name: c for name, c in curves.items() if len(c["step"])}
    if not curves:
        return (
            "<p>No validation curve: stage.warmup.validation.every and stage.dynamic.validation.every "
            "are 0 (docs/how-to/quality-during-training.md).</p>"
        )
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3), dpi=100)
    with_lpips = any(np.isfinite(np.asarray(c["lpips"], float)).any() for c in curves.values())
    ax_lpips = ax.twinx() if with_lpips else None
    offset = 0.0
    for name, curve in curves.items():
        wall = np.asarray(curve["wall_s"], float) + offset
        (line,) = ax.plot(wall, curve["psnr"], marker=".", label=name)
        if ax_lpips is not None:  # validation.lpips: dashed, same colour, right axis
            ax_lpips.plot(wall, curve["lpips"], linestyle="--", marker=".", color=line.get_color())
        offset = float(wall[-1])
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("validation PSNR (dB)")
    if ax_lpips is not None:
        ax_lpips.set_ylabel("validation LPIPS (dashed)")
    ax.legend()
    title = "Validation PSNR" + (" and LPIPS" if with_lpips else "")
    return f"<h3>{title} during training (withheld training frames, training cameras)</h3>" + _png_image(
        "validation curve", _figure_png(fig)
    )


def _png_image(alt: str, png_base64: str) -> str:
    """An ``<img>`` of a base64 PNG (its alphabet needs no escaping) described by ``alt``."""
    return f"<img alt='{esc.text(alt)}' src='data:image/png;base64,{png_base64}'>"


def _base64_file(path: Path) -> str:
    """Base64 of a file (a PNG or a video) for a data URI."""
    return base64.b64encode(path.read_bytes()).decode()


#: the contact sheet's rows hold at most this many tiles, and are at most this many pixels wide (a page of 1280
#: CSS pixels less its margins; the page's CSS shrinks any wider image to fit as well)
SHEET_COLUMNS, SHEET_MAX_PX = 4, 1200


def _contact_sheet(frames_dir: Path, seq: str, camera_ids: list[str], frame: int, px: int) -> str:
    """Base64 PNG of every camera's crop of ``frame`` of ``seq``, ``px`` square each, in rows (:func:`tile_grid`)."""
    tiles = [
        cv2.resize(read_png(rgb_path(frames_dir, seq, cid, frame), 3), (px, px), interpolation=cv2.INTER_AREA)
        for cid in camera_ids
    ]
    return _image_png(tile_grid(tiles))


def tile_grid(
    tiles: Sequence[np.ndarray], columns: int = SHEET_COLUMNS, max_px: int = SHEET_MAX_PX, gap: int = 4
) -> np.ndarray:
    """(H, W, 3) uint8: ``tiles`` (each (h, w, 3), one size) row by row on white, ``gap`` pixels apart, as many per
    row as fit ``max_px`` up to ``columns`` (at least one)."""
    h, w = tiles[0].shape[:2]
    per_row = max(1, min(columns, len(tiles), (max_px + gap) // (w + gap)))
    rows = math.ceil(len(tiles) / per_row)
    grid = np.full((rows * (h + gap) - gap, per_row * (w + gap) - gap, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, per_row)
        grid[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = tile
    return grid


def _image_png(image: np.ndarray) -> str:
    """Base64 PNG of an (H, W, 3) uint8 RGB image."""
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    assert ok
    return base64.b64encode(png.tobytes()).decode()


def _table(headers: tuple[str, ...], rows: list[tuple]) -> str:
    """An HTML table of ``headers`` and ``rows`` (any values: each cell is ``str(value)``, escaped)."""
    head = "".join(f"<th>{esc.text(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{esc.text(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"
