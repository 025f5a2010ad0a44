"""Stage ``evaluate``: held-out camera (novel view) and held-out motion (self-reenactment) metrics.

The held-out motion is scored under one or two tracking protocols (``stage.evaluate.test_tracking``):

* ``tracker`` (split ``self_reenact``): posed with the fit's parameters, scored on every training camera;
* ``avatar`` (adds split ``self_reenact_tracked``): each frame's parameters first refined with the trained model
  frozen (:func:`avatar.training.avatar_tracking.track_with_avatar`) on the *tuning* training cameras
  (``stage.evaluate.tuning_cameras``), then scored on the *other* training cameras only: no view that tuned a
  frame scores it, and the held-out camera is never read. The ``self_reenact`` rows of those scoring cameras
  are the tracker protocol on the same views (``self_reenact_scoring_psnr``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import (
    contact_frames,
    load_ground_truth_params,
    load_params,
    load_scene,
    load_views,
    method_params,
    write_params,
)
from avatar.artifacts.dependencies import contact_sources, unused_driving_settings
from avatar.artifacts.motion import applied_deformation, load_sequence, posed_sequence, posed_with_offsets, templates
from avatar.device import host
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.fitting.errors import tracking_errors
from avatar.geometry.views import ViewSet
from avatar.metrics import LPIPS, image_metrics
from avatar.posing import MeshSequence
from avatar.preprocess.crops import label_box, overlap_box
from avatar.reenact.driving import drive, driver_subject, transfer_summary, transferred_params
from avatar.render.gaussians import WorldGaussians, resolve_backend
from avatar.representations import TrainedAvatar, frame_pose, load_trained
from avatar.synthetic.rig import held_out_index
from avatar.templates import TemplateModel
from avatar.training.avatar_tracking import (
    AvatarTrackingConfig,
    TrackedMotion,
    track_with_avatar,
    tracking_cameras,
    untracked_reason,
)
from avatar.training.frame_params import parameter_movement
from avatar.training.rendering import rasterize
from data_schemas.cameras import read_cameras
from data_schemas.capture import MASK_LABELS, CaptureIndex, cross_sequence
from data_schemas.config_sections import core_config
from data_schemas.frames import UNOBSERVED
from data_schemas.images import to_uint8, write_png
from data_schemas.metrics import METRICS, REGIONS, SPLIT_SOURCES, TRACKED_SPLIT, showcase_path
from data_schemas.tables import SchemaError, write_table
from data_schemas.writes import write_json
from pipeline.config import synthetic_camera_ids
from pipeline.stage import StageContext, stage

TEST_TRACKING = ("tracker", "avatar")
#: folder of the held-out motion's parameters as the avatar tracked it (``tracking/<sequence>/params.parquet``)
TRACKING_DIR = "tracking"


@dataclass
class EvaluateConfig:
    """Types of ``stage.evaluate`` (values in conf/stage/evaluate.yaml)."""

    grid_samples: int
    showcase_frames: int
    backend: str
    test_tracking: str
    tuning_cameras: Any  # "auto" or a list of training camera ids
    tracking: AvatarTrackingConfig

    @classmethod
    def validate(cls, conf: Any) -> list[str]:
        """Range problems of a ``stage.evaluate`` section, one line each, keyed relative to it."""
        problems = (
            []
            if conf.test_tracking in TEST_TRACKING
            else [f"test_tracking={conf.test_tracking}: choose one of {', '.join(TEST_TRACKING)}"]
        )
        cams = conf.tuning_cameras
        listed = not isinstance(cams, str) and len(cams) > 0 and all(isinstance(c, str) for c in cams)
        if not (cams == "auto" or listed):
            problems.append(f"tuning_cameras={cams}: 'auto' or a non-empty list of training camera ids")
        elif listed and (twice := sorted({c for c in cams if list(cams).count(c) > 1})):
            problems.append(f"tuning_cameras={list(cams)}: {', '.join(twice)} listed more than once; name each once")
        problems += [f"tracking.{p}" for p in core_config(AvatarTrackingConfig, conf.tracking).problems()]
        return problems


def unused_evaluate_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What evaluate never reads in this configuration: the PBD solver's settings it does not drive with
    (:func:`unused_driving_settings`) and, where the held-out motion is posed as the tracker tracked it
    (``test_tracking=tracker``), the avatar tracking's."""
    tracked = str(cfg.stage.evaluate.test_tracking) == "avatar"
    return unused_driving_settings(cfg) + (
        () if tracked else ("stage.evaluate.tuning_cameras", "stage.evaluate.tracking")
    )


def known_train_cameras(cfg: DictConfig) -> tuple[list[str], list[str]] | None:
    """(training, held-out) camera ids of the capture, where they are known before it runs: the synthetic rig's, or
    those ``dataset.train_cameras`` names (the held-out ones then unknown: empty); None otherwise."""
    dataset = cfg.dataset
    named = dataset.get("train_cameras")
    train = None if named is None else [str(c) for c in named]
    if dataset.get("name") != "synthetic":
        return None if train is None else (train, [])
    ids = synthetic_camera_ids(cfg)
    if train is None:
        train = [c for i, c in enumerate(ids) if i != held_out_index(len(ids))]
    return train, [c for c in ids if c not in train]


def tuning_camera_problems(cfg: DictConfig) -> list[str]:
    """With ``test_tracking=avatar``, ``stage.evaluate.tuning_cameras`` against the capture's training cameras where
    they are known before any stage runs (:func:`known_train_cameras`): one line for a held-out or unknown camera, or
    for a list that leaves no camera to score on."""
    conf = cfg.stage.evaluate
    known = known_train_cameras(cfg)
    if str(conf.test_tracking) != "avatar" or isinstance(conf.tuning_cameras, str) or known is None:
        return []
    train, held_out = known
    if untracked_reason(train) is not None:  # a monocular capture: evaluate skips the split, saying why
        return []
    wanted = [str(c) for c in conf.tuning_cameras]
    if held := [c for c in wanted if c in held_out]:
        return [
            f"stage.evaluate.tuning_cameras={wanted}: {', '.join(held)} held out (the novel view), which evaluate "
            f"never tracks on; name training cameras among {train}"
        ]
    try:
        tracking_cameras(wanted, train)
    except SchemaError as exc:
        return [str(exc)]
    return []


Renderer = Callable[[int, int], torch.Tensor]


# version 9: SSIM filtered by shifted sums instead of conv2d (rounding-level changes)
@stage(
    "evaluate",
    inputs=("capture", "frames", "fit", "scene", "pbd", "dynamic"),
    config_keys=("model", "method", "stage.evaluate", "reenact", "stage.pbd.solver"),
    outputs=("metrics.parquet", "grids", "renders", "splits.json", TRACKING_DIR),
    # 12: stage.evaluate.test_tracking (the held-out motion tracked by the avatar); 13: that tracking reuses the
    # networks' products of the fixed per-Gaussian inputs and poses its frames in batches (its parameters and the
    # self_reenact_tracked rows change by rounding; test_tracking=tracker writes the same bytes)
    version="13",
    device=True,
    precision=True,
    config_schema=EvaluateConfig,
    sources=contact_sources,
    per_method=True,
    subject_inputs=("fit",),
    input_subject=driver_subject,
    unused_keys=unused_evaluate_settings,
    checks=tuning_camera_problems,
)
def evaluate(ctx: StageContext) -> None:
    """Render the held-out camera and the held-out motion (and, when reenact.driver names another subject
    whose motion the capture has this identity perform, that cross-actor reenactment) with the method's
    trained model; PSNR/SSIM/LPIPS per region; image grids; the renders of the showcase contact frames. With
    ``test_tracking=avatar`` the held-out motion also tracked by the avatar (module docstring)."""
    conf, method = ctx.cfg.stage.evaluate, str(ctx.cfg.method.name)
    cap_dir, frames_dir = ctx.input_dir("capture"), ctx.input_dir("frames")
    rows: dict[str, list] = {c.name: [] for c in METRICS.columns}
    lpips = LPIPS("alex").to(ctx.device)
    # what backend=auto chose here, for tensors on the run's device
    ctx.metrics["rasterizer"] = resolve_backend(conf.backend, torch.zeros(0, 3, device=ctx.device))
    model = load_trained(ctx.input_dir("dynamic")).on_device(ctx.device, ctx.precision)
    (ctx.out_dir / "grids").mkdir()
    (ctx.out_dir / TRACKING_DIR).mkdir()
    splits = _splits(ctx)
    for split, why in _unmeasurable(cap_dir, splits).items():  # e.g. a monocular capture has no held-out camera
        del splits[split]
        ctx.metrics[f"{split}_skipped"] = why
    if TRACKED_SPLIT in splits:  # tuning cameras the capture does not train on: said before any split renders
        tracking_cameras(
            conf.tuning_cameras, [c.camera_id for c in read_cameras(cap_dir / "cameras.parquet") if c.split == "train"]
        )
    write_json(
        ctx.out_dir / "splits.json",
        {split: sequence for split, (sequence, _) in splits.items()},
        "the sequence each split renders",
    )
    loaded: dict[tuple[str, str], ViewSet] = {}  # the held-out motion's crops serve both of its protocols
    for split, (sequence, camera_split) in splits.items():
        if (sequence, camera_split) not in loaded:
            loaded[sequence, camera_split] = load_views(cap_dir, frames_dir, sequence, camera_split, ctx.device)
        views = loaded[sequence, camera_split]
        if split == TRACKED_SPLIT:
            tuning, scoring = tracking_cameras(conf.tuning_cameras, views.camera_ids)
            ctx.metrics["tracking_scoring_cameras"] = ",".join(scoring)
            meshes, cond = _tracked_sequence(ctx, model, sequence, views.cameras(tuning))
            views = views.cameras(scoring)
        else:
            meshes, cond = _split_sequence(ctx, split, sequence, views.num_frames)
        render = _renderer(model, cond.to(ctx.device), meshes.to(ctx.device), views, conf.backend)
        labels = views.labels.cpu()  # the regions' masks, cut on the host
        contact = contact_frames(cap_dir, sequence, views.num_frames)
        showcase = set(showcase_pairs(contact, int(conf.showcase_frames)))
        (ctx.out_dir / "renders" / split).mkdir(parents=True)
        pairs = [(t, c) for t in range(views.num_frames) for c in range(views.num_cameras)]
        grid: list[np.ndarray] = []
        for i, (t, c) in enumerate(ctx.progress(pairs, desc=f"evaluate {split}")):
            with torch.no_grad():
                raw = render(t, c).clamp(0, 1)
            # metrics and error maps on the observed pixels only: the render takes the ground truth on padding
            gt, pred = (image.permute(2, 0, 1) for image in views.target_and_render(raw, t, c))
            for region, mask in _regions(labels[t, c].numpy()).items():
                m = image_metrics(pred, gt, None if mask is None else torch.from_numpy(mask), lpips_model=lpips)
                for key, value in (
                    ("method", method),
                    ("split", split),
                    ("camera_id", views.camera_ids[c]),
                    ("frame", t),
                    ("region", region),
                    ("contact", bool(contact[t])),
                    ("psnr", m["psnr"]),
                    ("ssim", m["ssim"]),
                    ("lpips", m["lpips"]),
                ):
                    rows[key].append(value)
            if (t, c) in showcase:
                write_png(showcase_path(ctx.out_dir, split, t, views.camera_ids[c]), _to_u8(raw.permute(2, 0, 1)))
            if i % max(len(pairs) // max(conf.grid_samples, 1), 1) == 0 and len(grid) < conf.grid_samples:
                grid.append(_grid_row(gt, [pred]))
        write_png(ctx.out_dir / "grids" / f"{split}.png", np.concatenate(grid, axis=0))
    write_table(
        ctx.out_dir / "metrics.parquet",
        METRICS,
        {k: (v if METRICS.column(k).kind == "string" else np.asarray(v)) for k, v in rows.items()},
    )
    ctx.metrics.update(_summary(rows))
    if TRACKED_SPLIT in splits:
        ctx.metrics.update(_scoring_summary(rows, str(ctx.metrics["tracking_scoring_cameras"]).split(",")))


def _tracked_sequence(
    ctx: StageContext, model: TrainedAvatar, sequence: str, tuning: ViewSet
) -> tuple[MeshSequence, SequenceConditioning]:
    """The held-out motion's meshes and conditioning after :func:`track_with_avatar` refined each frame's parameters
    with ``model`` frozen, from the ``tuning`` views alone (the fit's parameters and the pbd stage's offsets to
    start from; the offsets stay). Writes ``tracking/<sequence>/params.parquet`` and the manifest's ``tracking_*``
    (on a capture with ground truth also the 3D errors of the fit's and the refined parameters, mm)."""
    cfg = ctx.cfg
    fit_dir = ctx.input_dir("fit")
    posed = posed_sequence(
        fit_dir,
        sequence,
        cfg,
        applied_deformation(cfg, ctx.input_dir("pbd")),
        method_params(ctx.input_dir("dynamic"), fit_dir, sequence),
    )
    head, hand = templates(cfg.model)
    started = time.perf_counter()
    tracked = track_with_avatar(
        frame_pose(model),
        posed.params,
        head,
        hand,
        torch.from_numpy(posed.offsets).float(),
        tuning,  # on the run's device, as the avatar
        core_config(AvatarTrackingConfig, cfg.stage.evaluate.tracking),
        str(cfg.stage.evaluate.backend),
        progress=lambda steps: ctx.progress(steps, desc=f"track {sequence} with the avatar"),
    )
    seconds = time.perf_counter() - started
    (ctx.out_dir / TRACKING_DIR / sequence).mkdir()
    write_params(ctx.out_dir / TRACKING_DIR / sequence / "params.parquet", tracked.params)
    ctx.metrics.update(_tracking_summary(tracked, posed.params, tuning, seconds, head, hand))
    if CaptureIndex.read(ctx.input_dir("capture")).sequences[sequence].has_ground_truth:  # synthetic: how far off
        truth = load_ground_truth_params(ctx.input_dir("capture"), sequence)
        for name, values in (("before", posed.params), ("after", tracked.params)):
            errors = tracking_errors(values, truth, head, hand)
            ctx.metrics.update({f"tracking_{name}_{k}": v for k, v in errors.items()})
    retracked = posed_with_offsets(tracked.params, cfg, posed.offsets)
    return retracked.meshes, retracked.conditioning(cfg)


def _tracking_summary(
    tracked: TrackedMotion,
    before: dict[str, np.ndarray],
    tuning: ViewSet,
    seconds: float,
    head: TemplateModel,
    hand: TemplateModel,
) -> dict[str, Any]:
    """The manifest's ``tracking_*`` entries: cameras, losses before and after, how far the parts moved, the frames
    that kept a part as tracked, and the time per frame and tuning view."""
    moved = parameter_movement(before, tracked.params, head, hand)
    out: dict[str, Any] = {
        "tracking_tuning_cameras": ",".join(tuning.camera_ids),
        "tracking_loss_before": float(tracked.loss_before.mean()),
        "tracking_loss_after": float(tracked.loss_after.mean()),
        "tracking_seconds": seconds,
        "tracking_ms_per_frame_view": 1e3 * seconds / max(tuning.num_frames * tuning.num_cameras, 1),
    }
    for part in ("face", "hand"):
        out[f"tracking_moved_{part}_mm_mean"] = float(moved["moved_mm"][part].mean())
        out[f"tracking_moved_{part}_mm_max"] = float(moved["moved_mm"][part].max())
        out[f"tracking_held_{part}_frames"] = int(tracked.held[part].sum())
    return out


def _scoring_summary(rows: dict[str, list], scoring: list[str]) -> dict[str, float]:
    """The tracker protocol's full-image PSNR/LPIPS of the held-out motion on the scoring cameras alone (the views
    the avatar-tracked split is scored on)."""
    keep = [
        i
        for i, (s, r, c) in enumerate(zip(rows["split"], rows["region"], rows["camera_id"]))
        if s == "self_reenact" and r == "full" and c in scoring
    ]
    return {f"self_reenact_scoring_{m}": float(np.nanmean([rows[m][i] for i in keep])) for m in ("psnr", "lpips")}


def _renderer(
    model: TrainedAvatar, cond: SequenceConditioning, meshes: MeshSequence, views: ViewSet, backend: str
) -> Renderer:
    """Frame ``t`` of the sequence (``cond``, ``meshes``) rendered from camera ``c`` of ``views``, (S, S, 3). The
    frame is posed once for all its cameras: the Gaussians of the last frame asked for are kept."""
    posed: dict[int, WorldGaussians] = {}

    def render(t: int, c: int) -> torch.Tensor:
        if t not in posed:
            posed.clear()
            posed[t] = model.pose(cond, meshes.vertices[t], t)
        return rasterize(posed[t], views, c, backend).rgb

    return render


def _unmeasurable(cap_dir: Path, splits: dict[str, tuple[str, str]]) -> dict[str, str]:
    """split -> why it cannot be measured on this capture: its sequence or its cameras are missing, or (the
    avatar-tracked split) one camera would have to both tune and score (:func:`untracked_reason`)."""
    sequences = CaptureIndex.read(cap_dir).sequences
    cameras = read_cameras(cap_dir / "cameras.parquet")
    why = {}
    for split, (sequence, camera_split) in splits.items():
        ids = [c.camera_id for c in cameras if c.split == camera_split]
        if sequence not in sequences:
            why[split] = f"the capture has no '{sequence}' sequence"
        elif not ids:
            why[split] = f"the capture has no '{camera_split}' camera (a held-out view)"
        elif split == TRACKED_SPLIT and (untracked := untracked_reason(ids)) is not None:
            why[split] = untracked
    return why


def _splits(ctx: StageContext) -> dict[str, tuple[str, str]]:
    """split -> (sequence, camera split): novel view and self-reenactment (with ``test_tracking=avatar`` also
    the avatar-tracked self-reenactment), and cross-actor reenactment when ``reenact.driver`` names another subject
    and the capture holds its ground truth."""
    splits = dict(SPLIT_SOURCES)
    if ctx.cfg.stage.evaluate.test_tracking == "avatar":
        splits[TRACKED_SPLIT] = SPLIT_SOURCES["self_reenact"]
    driver = driver_subject(ctx.cfg)
    if driver is not None:
        sequence = cross_sequence(driver)
        if sequence in CaptureIndex.read(ctx.input_dir("capture")).sequences:
            splits["cross_reenact"] = (sequence, "train")
        ctx.metrics["cross_reenact"] = sequence if "cross_reenact" in splits else "no ground truth in the capture"
    return splits


def _split_sequence(
    ctx: StageContext, split: str, sequence: str, num_frames: int
) -> tuple[MeshSequence, SequenceConditioning]:
    """The meshes and conditioning a split renders: the fit of its sequence (the train motion as the method refined
    it: :func:`method_params`; with the pbd stage's offsets when the method uses them), or for cross-actor
    reenactment the driver's motion transferred onto this subject with its contact simulated, exactly as stage
    reenact does."""
    if split != "cross_reenact":
        pbd_dir, fit_dir = applied_deformation(ctx.cfg, ctx.input_dir("pbd")), ctx.input_dir("fit")
        return load_sequence(
            fit_dir,
            sequence,
            ctx.cfg,
            pbd_dir=pbd_dir,
            params=method_params(ctx.input_dir("dynamic"), fit_dir, sequence),
        )
    driver_sequence = str(ctx.cfg.reenact.sequence)
    path = ctx.subject_input_dir("fit") / driver_sequence / "params.parquet"
    params = load_params(ctx.subject_input_dir("fit"), driver_sequence)
    if len(params["flame_global_orient"]) != num_frames:
        raise SchemaError(
            f"{path}: {len(params['flame_global_orient'])} frames, but the ground truth "
            f"'{sequence}' of the capture has {num_frames}; fit the driver at the same preset"
        )
    transfer = transferred_params(ctx.cfg, ctx.input_dir("fit"), params, path)
    driven = drive(ctx.cfg, transfer.params, load_scene(ctx.input_dir("scene")), transfer.head_scale)
    ctx.metrics["cross_reenact_head_scale"] = transfer.head_scale
    ctx.metrics.update({f"cross_reenact_{k}": v for k, v in transfer_summary(transfer.frames).items()})
    return driven.meshes, driven.cond


def showcase_pairs(contact: np.ndarray, count: int) -> list[tuple[int, int]]:
    """(frame, camera index 0) of up to ``count`` frames spread evenly over the contact frames (over all frames
    when none has contact): the same for every method, so their renders line up in the comparison."""
    frames = np.flatnonzero(contact) if contact.any() else np.arange(len(contact))
    picks = np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))
    return [(int(frames[i]), 0) for i in picks] if count > 0 else []


def _summary(rows: dict[str, list]) -> dict[str, float]:
    """Mean full-image metrics per split (and PSNR over the frames without contact)."""
    out = {}
    for split in dict.fromkeys(rows["split"]):
        full = [i for i, (s, r) in enumerate(zip(rows["split"], rows["region"])) if s == split and r == "full"]
        for metric in ("psnr", "ssim", "lpips"):
            out[f"{split}_{metric}"] = float(np.nanmean([rows[metric][i] for i in full]))
        no_contact = [rows["psnr"][i] for i in full if not rows["contact"][i]]
        if no_contact:
            out[f"{split}_psnr_no_contact"] = float(np.nanmean(no_contact))
    return out


def _regions(labels: np.ndarray) -> dict[str, np.ndarray | None]:
    """Region masks (S, S) bool of one crop; ``full`` is the observed pixels (None when the camera saw every
    pixel of the crop; crop padding past its image is left out). ``interaction`` is the overlap of the hand
    and face boxes, empty when they do not overlap."""
    observed = labels != UNOBSERVED
    hand, face = labels == MASK_LABELS["hand"], labels == MASK_LABELS["face"]
    interaction = np.zeros_like(hand)
    box = overlap_box(label_box(labels, MASK_LABELS["hand"]), label_box(labels, MASK_LABELS["face"]))
    if box is not None:
        x0, y0, x1, y1 = box.astype(int)
        interaction[y0:y1, x0:x1] = True
    masks: dict[str, np.ndarray | None] = {
        "full": None if observed.all() else observed,
        "hand": hand,
        "face": face,
        "interaction": interaction,
    }
    assert tuple(masks) == REGIONS
    return masks


def _to_u8(image: torch.Tensor) -> np.ndarray:
    """(S, S, 3) uint8 of an image (3, S, S) in [0, 1]."""
    return to_uint8(host(image.permute(1, 2, 0)))


def _grid_row(gt: torch.Tensor, preds: list[torch.Tensor]) -> np.ndarray:
    """(S, (1 + 2M) S, 3) uint8: ground truth | each method's render | each method's error heat map (x4);
    images (3, S, S) in [0, 1]."""

    def heat(pred: torch.Tensor) -> np.ndarray:
        err = (host((pred - gt).abs().mean(0)) * 4 * 255).clip(0, 255).astype(np.uint8)
        return cv2.applyColorMap(err, cv2.COLORMAP_INFERNO)[..., ::-1]

    return np.concatenate([_to_u8(gt), *(_to_u8(p) for p in preds), *(heat(p) for p in preds)], axis=1)
