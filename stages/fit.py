"""Stage ``fit``: per-frame FLAME/MANO parameters from multi-view keypoints (or ground truth)."""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from avatar.artifacts import load_ground_truth_params, load_provided_params, load_views
from avatar.artifacts.dependencies import TEMPLATE_KEYS, model_file_problems, model_sources
from avatar.artifacts.motion import templates
from avatar.fitting.errors import tracking_errors
from avatar.fitting.fit import FitConfig, FitResult, WorldScaleError, face_shape_columns, fit_sequence
from avatar.fitting.observations import keypoints_by_camera
from avatar.fitting.refine import (
    REFINE_MODES,
    RefineConfig,
    RefineResult,
    evidence_from_views,
    tracking_outlines,
)
from avatar.geometry.views import ViewSet
from avatar.templates import TemplateModel
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex
from data_schemas.config_sections import core_config, section_schema
from data_schemas.images import write_png
from data_schemas.keypoints import KEYPOINTS
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import SchemaError, read_table, write_table
from data_schemas.writes import write_json
from pipeline.manifest import hash_outputs
from pipeline.stage import StageContext, stage

SOURCES = ("ground_truth", "provided", "fitted")
#: stage.fit.refine: a mode of avatar.fitting.refine, or auto (see :func:`refine_mode`)
REFINE_CHOICES = ("auto", *REFINE_MODES)
#: <sequence>/refinement.png: the keypoint fit's and the refined meshes' outlines over a training crop
REFINEMENT_FIGURE = "refinement.png"
#: fit.source=fitted, a sequence without any hand keypoint in the train views (a capture without a hand, e.g. the
#: synthetic face_only scene; fit_report.json: "hand_fitted": false) gets a placeholder hand, not a fit: MANO's
#: mean shape in its flat rest pose, unrotated, this far (metres) below the fitted head's translation (world -y):
#: finite, and far from the face, so that no later stage finds it touching the face.
ABSENT_HAND_DROP_M = 2.0

log = logging.getLogger(__name__)


@dataclass
class FitStageSettings:
    """The fit stage's own settings: those the fitting's :class:`FitConfig` does not hold."""

    identity_space: str
    refine: str
    refinement: RefineConfig

    @staticmethod
    def validate(conf: Any) -> list[str]:
        problems = (
            []
            if conf.refine in REFINE_CHOICES
            else [f"refine={conf.refine}: choose one of {', '.join(REFINE_CHOICES)}"]
        )
        problems += [
            f"refinement.{key}={getattr(conf.refinement, key)}: must be at least 1"
            for key in ("render_size", "exact_every")
            if getattr(conf.refinement, key) < 1
        ]
        return problems


#: Types of ``stage.fit`` (values in conf/stage/fit.yaml): every setting of the fitting's :class:`FitConfig` (its
#: identity columns come from ``identity_space``) and the stage's own.
FitStageConfig = section_schema("FitStageConfig", FitConfig, exclude=("face_shape_columns",), own=FitStageSettings)


@stage(
    "fit",
    inputs=("capture", "frames", "keypoints"),
    config_keys=("fit.source", *TEMPLATE_KEYS, "stage.fit", "stage.keypoints.detector"),
    outputs=("train/params.parquet", "fit_report.json"),
    version="8",  # 8: image refinement (stage.fit.refine), keypoint-fit errors kept beside the refined ones
    config_schema=FitStageConfig,
    sources=model_sources,
    checks=model_file_problems,
)
def fit(ctx: StageContext) -> None:
    """Write params.parquet per sequence from fit.source, and fit_report.json with the errors and, per sequence,
    whether the hand was fitted (false: no hand keypoint to fit, see :data:`ABSENT_HAND_DROP_M`). With
    fit.source=fitted and stage.fit.refine not none, the keypoint fit is refined by the train views' crops
    (never the held-out camera's) and the report keeps the keypoint fit's errors under ``keypoint_fit``."""
    source = ctx.cfg.fit.source
    if source not in SOURCES:
        raise SchemaError(f"fit.source={source!r}: choose one of {SOURCES}")
    refine_cfg = RefineConfig(**ctx.cfg.stage.fit.refinement)
    cap_dir = ctx.input_dir("capture")
    index = CaptureIndex.read(cap_dir)
    head, hand = templates(ctx.cfg.model)
    cameras = [c for c in read_cameras(cap_dir / "cameras.parquet") if c.split == "train"]
    section = ctx.cfg.stage.fit
    identity_columns = face_shape_columns(head, str(section.identity_space), str(ctx.cfg.stage.keypoints.detector))
    conf = core_config(FitConfig, section, face_shape_columns=identity_columns)
    # train_views: 1 is a monocular fit (avatar.fitting.monocular): depth comes from the templates' sizes.
    report: dict = {"source": source, "train_views": len(cameras), "sequences": {}}
    refine = refine_mode(str(ctx.cfg.stage.fit.refine), str(ctx.cfg.stage.keypoints.detector), len(cameras))
    if source == "fitted":
        report["refine"] = refine
        report["refine_setting"] = str(ctx.cfg.stage.fit.refine)
    checkpoints = SequenceCheckpoints(ctx.scratch_dir / "sequences") if ctx.scratch_dir is not None else None
    for seq, info in ctx.progress(list(index.sequences.items()), desc="fit: sequences"):
        resumed = checkpoints.restore(seq, ctx.out_dir / seq) if checkpoints is not None else None
        if resumed is not None:  # fitted by a run that was stopped later (a SLURM requeue at the time limit)
            entry, metrics = resumed
            log.info("fit: sequence %s resumed from a checkpoint", seq)
            report["sequences"][seq] = entry
            ctx.metrics.update(metrics)
            continue
        metrics_before = dict(ctx.metrics)
        hand_fitted = True
        if source == "ground_truth":
            params = load_ground_truth_params(cap_dir, seq)
            entry = {}
        elif source == "provided":
            params = load_provided_params(cap_dir, seq)
            entry = {}
        else:
            kp = keypoints_by_camera(
                read_table(ctx.input_dir("keypoints") / seq / "keypoints.parquet", KEYPOINTS), info.num_frames
            )
            # Only the train views: the held-out camera's detections would leak the novel view into the fit.
            train_kp = {c.camera_id: kp[c.camera_id] for c in cameras if c.camera_id in kp}
            hand_fitted = _sees_hand(train_kp)
            evidence = None
            if refine != "none":  # the train views only: the held-out camera never informs the tracking
                views = load_views(cap_dir, ctx.input_dir("frames"), seq, "train")
                _check_evidence(views.labels, ctx.input_dir("frames"), seq)
                evidence = evidence_from_views(views, refine_cfg.render_size)
            # Without any hand keypoint the hand stays where its initialisation puts it, inside the head, and the
            # interpenetration term pushes the face: fit the face alone, then write the placeholder hand.
            try:
                result = fit_sequence(
                    train_kp,
                    cameras,
                    head,
                    hand,
                    conf if hand_fitted else replace(conf, penetration_mm=0.0),
                    evidence,
                    refine,
                    refine_cfg,
                )
            except WorldScaleError as exc:
                raise SchemaError(f"{cap_dir / 'cameras.parquet'}: {exc}") from exc
            params = result.params if hand_fitted else _placeholder_hand(result.params)
            entry = _fit_entry(result)
            if result.refinement is not None:
                entry["refinement"] = _refinement_entry(result.refinement, hand_fitted)
                _write_overlay(ctx.out_dir / seq / REFINEMENT_FIGURE, views, result, head, hand, hand_fitted)
                keypoint_only = _fit_entry(result, keypoint_fit=True)
                if info.has_ground_truth:
                    keypoint_params = (
                        result.keypoint_params if hand_fitted else _placeholder_hand(result.keypoint_params)
                    )
                    errors = tracking_errors(keypoint_params, load_ground_truth_params(cap_dir, seq), head, hand)
                    keypoint_only.update({k: v for k, v in errors.items() if hand_fitted or "hand" not in k})
                entry["keypoint_fit"] = keypoint_only
                ctx.metrics[f"{seq}_refine_ms_per_frame_per_view"] = (
                    1e3 * result.refinement.seconds / info.num_frames / len(cameras)
                )
            # Timings go to the manifest (its metrics), never into an artifact: a rerun must write the same bytes.
            ctx.metrics[f"{seq}_fit_ms_per_frame_per_view"] = (
                1e3 * result.timing.get("total_s", 0.0) / info.num_frames / len(cameras)
            )
        entry["hand_fitted"] = hand_fitted
        if info.has_ground_truth:
            errors = tracking_errors(params, load_ground_truth_params(cap_dir, seq), head, hand)
            entry.update({k: v for k, v in errors.items() if hand_fitted or "hand" not in k})
        write_table(
            ctx.out_dir / seq / "params.parquet",
            PARAMS,
            {"frame": np.arange(info.num_frames), **{k: params[k] for k in PARAM_COLUMNS}},
        )
        report["sequences"][seq] = entry
        for key in ("mpjpe_hand_mm", "mpjpe_face_mm"):
            if key in entry:
                ctx.metrics[f"{seq}_{key}"] = entry[key]
        if checkpoints is not None:
            checkpoints.save(
                seq, ctx.out_dir / seq, entry, {k: v for k, v in ctx.metrics.items() if metrics_before.get(k) != v}
            )
    write_json(ctx.out_dir / "fit_report.json", report, "fit report")


class SequenceCheckpoints:
    """Sequences already fitted by a stopped run of this stage (same cache key): the sequence's output folder
    and its report entry and metrics, kept in the stage's scratch dir so that a rerun (a job requeued at its
    time limit) resumes after the last fitted sequence instead of refitting everything. Each sequence is saved
    whole or not at all (written aside, then renamed) with the sha256 of every file; one that fails to verify
    is logged, deleted and fitted again. Resuming reproduces the uninterrupted run's bytes."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def save(self, seq: str, out: Path, entry: dict, metrics: dict) -> None:
        """Keep ``out`` (the sequence's output folder), its report ``entry`` and its ``metrics``."""
        tmp = self.root / f".{seq}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(out, tmp / "out")
        write_json(
            tmp / "entry.json",
            {"entry": entry, "metrics": metrics, "sha256": hash_outputs(tmp / "out")},
            "fit checkpoint",
        )
        shutil.rmtree(self.root / seq, ignore_errors=True)
        os.replace(tmp, self.root / seq)

    def restore(self, seq: str, out: Path) -> tuple[dict, dict] | None:
        """Copy a saved ``seq`` back to ``out``; its (report entry, metrics), or ``None`` if none was saved or
        it failed to verify (then it is deleted)."""
        saved = self.root / seq
        if not (saved / "entry.json").is_file():
            return None
        try:
            data = json.loads((saved / "entry.json").read_text())
            if hash_outputs(saved / "out") != data["sha256"]:
                raise ValueError("a file's sha256 differs from the one saved with it")
            entry, metrics = data["entry"], data["metrics"]
        except (ValueError, KeyError, TypeError, OSError) as exc:
            log.warning("fit: the checkpoint of sequence %s (%s) is unusable (%s): fitting it again", seq, saved, exc)
            shutil.rmtree(saved, ignore_errors=True)
            return None
        shutil.copytree(saved / "out", out)
        return entry, metrics


def refine_mode(setting: str, detector: str, train_views: int) -> str:
    """The image refinement ``stage.fit.refine=setting`` asks for: a mode as given, or for ``auto`` the
    silhouettes where they were measured to help (docs/explanation/tracking-refinement.md): MediaPipe's
    keypoints seen by two or more training views. Not with the synthetic ground-truth keypoints (at 1 px their
    fit is finer than 64 px silhouettes, which made it worse: hand 1.9 -> 2.5 mm), not from one view (the
    outline does not fix the distance: the face went from 58 to 71 mm), and not with a dataset's own keypoints
    (``provided``: DECAF's masks label the whole matte but the hand as face, neck and shoulders too, which no
    head mesh covers)."""
    if setting != "auto":
        return setting
    return "silhouette" if detector == "mediapipe" and train_views >= 2 else "none"


def _write_overlay(
    path: Path, views: ViewSet, result: FitResult, head: TemplateModel, hand: TemplateModel, hand_fitted: bool
) -> None:
    """The keypoint fit's (red) and the refined (green) mesh outlines over the first training view's crop, in the
    frame where the refinement moved the meshes most."""
    assert result.refinement is not None  # called only for a fit the image refinement ran on
    moved = result.refinement.moved_mm["hand"] if hand_fitted else result.refinement.moved_mm["face"]
    frame = int(np.argmax(moved))
    write_png(
        path,
        tracking_outlines(
            views.images[frame, 0].numpy(),
            views.K[0],
            views.world_to_cam[0],
            [result.keypoint_params, result.params],
            frame,
            head,
            hand,
            hand_fitted,
        ),
    )


def _fit_entry(result: FitResult, keypoint_fit: bool = False) -> dict:
    """The report's reprojection errors and weakly constrained frames of the written parameters (or, with
    ``keypoint_fit``, of the keypoint fit before the image refinement)."""
    reprojection = result.keypoint_reprojection_px if keypoint_fit else result.reprojection_px
    return {
        "reprojection_px": {p: float(np.nanmean(v)) for p, v in reprojection.items() if np.isfinite(v).any()},
        "weak_frames": {p: np.flatnonzero(v).tolist() for p, v in result.weak_frames.items()},
    }


def _refinement_entry(refinement: RefineResult, hand_fitted: bool) -> dict:
    """What the image refinement did, for fit_report.json: silhouette IoU per part and view before and after,
    and per frame how far each part moved (mean vertex displacement, mm; change of global rotation, degrees).
    The hand is left out where no hand was fitted."""
    parts = [p for p in ("face", "hand") if hand_fitted or p != "hand"]
    return {
        "iterations": len(refinement.losses),
        "loss": {"first": float(refinement.losses[0]), "last": float(refinement.losses[-1])}
        if len(refinement.losses)
        else {},
        "silhouette_iou": {
            stage: {p: iou[p] for p in parts}
            for stage, iou in (
                ("keypoint_fit", refinement.silhouette_iou["before"]),
                ("refined", refinement.silhouette_iou["after"]),
            )
        },
        "moved_mm": {p: np.round(refinement.moved_mm[p], 4).tolist() for p in parts},
        "rotated_deg": {p: np.round(refinement.rotated_deg[p], 4).tolist() for p in parts},
        "unseen_frames": {p: refinement.frozen[p] for p in parts},
    }


def _check_evidence(labels: torch.Tensor, frames_dir: Path, sequence: str) -> None:
    """One clear error when the train views' masks of ``sequence`` (labels (T, C, S, S) uint8) hold no
    foreground at all: the refinement would pull the meshes out of every view."""
    if not ((labels >= 1) & (labels <= 3)).any():
        raise SchemaError(
            f"{frames_dir / sequence}/<camera>/mask/: every mask of the training cameras is empty "
            f"(no face, hand or foreground label): check the segmentation (stage.frames.segmenter, "
            f"stage.frames.key_threshold) and rerun frames, or set stage.fit.refine=none"
        )


def _sees_hand(keypoints: dict[str, dict[str, np.ndarray]]) -> bool:
    """Whether any view of ``keypoints`` (camera_id -> part -> (T, K, 3) rows of (u, v, confidence)) holds a
    hand keypoint with non-zero confidence."""
    return any((views["hand"][..., 2] > 0).any() for views in keypoints.values() if "hand" in views)


def _placeholder_hand(params: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``params`` (column -> (T, D)) with the MANO columns replaced by the placeholder hand of a sequence
    without hand keypoints (see :data:`ABSENT_HAND_DROP_M`)."""
    rest = {k: np.zeros_like(params[k]) for k in ("mano_shape", "mano_hand_pose", "mano_global_orient")}
    return {**params, **rest, "mano_transl": params["flame_transl"] - np.array([0.0, ABSENT_HAND_DROP_M, 0.0])}
