"""Stage ``viewer``: a page that plays the method's avatar in 3D in the browser (Spark on three.js).

It writes ``methods/<method>/viewer/``: ``index.html`` and ``viewer.js`` (the bundle ``make viewer`` builds from
``viewer/``), and ``data/``: the avatar's Gaussians once and, per motion, the posed vertices of every frame and the
Gaussians the frame changes beyond the codec's tolerances (:mod:`avatar.viewer.codec`), as scripts the page loads
from ``file://`` as well as from ``interactavatar-view``; the ground-truth crops of the capture cameras as JPEG;
``viewer.json``: sizes per frame and the quantisation error.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from omegaconf import DictConfig

from avatar.artifacts import HELD_OUT_SEQUENCE, TRAIN_SEQUENCE, contact_flags, load_views, method_params, read_params
from avatar.artifacts.dependencies import TEMPLATE_KEYS, model_files
from avatar.artifacts.motion import applied_deformation, posed_sequence, posed_with_offsets
from avatar.representations import load_trained
from avatar.viewer.codec import CodecConfig
from avatar.viewer.page import BUNDLE, PAGE_DIR, Motion, PageSettings, write_viewer
from data_schemas.capture import CaptureIndex
from data_schemas.config_sections import core_config, section_schema
from data_schemas.deform import DEFORM
from data_schemas.frames import FRAMES_INDEX
from data_schemas.sources import SourceFiles
from data_schemas.tables import SchemaError, read_table
from pipeline.stage import StageContext, stage

#: what stage reenact renders on by default (its report does not record stage.reenact.background); the page's
#: background is the first motion's, the capture's for the train and held-out motions
REENACT_BACKGROUND = [1.0, 1.0, 1.0]
#: the motions the viewer can offer, in its menu's order: the training motion, the held-out one, the reenactment
MOTIONS = ("train", "test", "reenact")


@dataclass
class ViewerSettings:
    """The stage's own settings (values in conf/stage/viewer.yaml)."""

    motions: list[str]
    reference_frames: int
    ground_truth: bool
    jpeg_quality: int
    fps: float

    @classmethod
    def validate(cls, conf: DictConfig) -> list[str]:
        """Range problems of a ``stage.viewer`` section (merged onto :data:`ViewerConfig`), one line each, keyed
        relative to ``stage.viewer``: the codec's tolerances, the motions (known ones, each once), the reference
        frames, the crops' JPEG quality (OpenCV's 1..100) and the playback rate (a page at 0 fps never advances)."""
        problems = core_config(CodecConfig, conf).problems()
        motions = list(conf.motions)
        if not motions or not set(motions) <= set(MOTIONS) or len(set(motions)) < len(motions):
            problems.append(f"motions={motions}: choose one or more of {list(MOTIONS)}, each once")
        if int(conf.reference_frames) < 1:
            problems.append(f"reference_frames={conf.reference_frames}: must be >= 1")
        if not 1 <= int(conf.jpeg_quality) <= 100:
            problems.append(f"jpeg_quality={conf.jpeg_quality}: must be between 1 and 100 (JPEG quality of the crops)")
        if not math.isfinite(float(conf.fps)) or float(conf.fps) <= 0:
            problems.append(f"fps={conf.fps}: must be > 0 (frames per second of the page's playback)")
        return problems


ViewerConfig = section_schema("ViewerConfig", CodecConfig, own=ViewerSettings)


def page_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # the SourceLister signature
    """The page's files (a rebuilt bundle reruns the stage) and the official model files (posing)."""
    page = [p for p in (PAGE_DIR / "index.html", BUNDLE) if p.is_file()]
    return SourceFiles(Path("/"), tuple(page + model_files(cfg)))


@stage(
    "viewer",
    inputs=("capture", "frames", "fit", "pbd", "dynamic", "reenact"),
    config_keys=(*TEMPLATE_KEYS, "method", "stage.viewer"),
    outputs=("index.html", "data", "viewer.json"),
    version="2",  # 2: names escaped in the page's data (data_schemas.web_escape)
    device=True,
    precision=True,
    config_schema=ViewerConfig,
    sources=page_sources,
    per_method=True,
)
def viewer(ctx: StageContext) -> None:
    """Write the browser viewer of the method's avatar: the page, its data per motion and frame, sizes and the
    quantisation error (viewer.json)."""
    conf = ctx.cfg.stage.viewer
    codec = core_config(CodecConfig, conf)
    motions = [m for m in (_motion(ctx, name) for name in conf.motions) if m is not None]
    if not motions:
        raise SchemaError(
            f"stage.viewer.motions={list(conf.motions)}: the capture has none of them; add reenact to play the "
            "reenactment"
        )
    settings = PageSettings(
        int(conf.reference_frames), bool(conf.ground_truth), int(conf.jpeg_quality), float(conf.fps)
    )
    identity = {"method": str(ctx.cfg.method.name), "label": str(ctx.cfg.method.label), "subject": ctx.subject}
    report = write_viewer(
        ctx.out_dir,
        load_trained(ctx.input_dir("dynamic")).on_device(ctx.device, ctx.precision),
        motions,
        codec,
        settings,
        identity,
        lambda frames, desc: ctx.progress(frames, desc=desc),
    )
    summaries = report["motions"]
    built, per_frame = report["page_built"], report["bytes_per_frame"]
    ctx.metrics.update(
        {
            "page_built": built,
            "gaussians": report["gaussians"],
            "bytes_per_frame": per_frame,
            "mb_per_100_frames": report["mb_per_100_frames"],
            **{
                key: float(np.mean([s[key] for s in summaries]))
                for key in ("geometry_overrides_per_frame", "appearance_overrides_per_frame")
            },
            **{
                key: max(s["errors"][key] for s in summaries)
                for key in ("geometry_mm_max", "position_mm_max", "color_levels_max", "opacity_levels_max")
            },
        }
    )


def _motion(ctx: StageContext, name: str) -> Motion | None:
    """The motion ``name`` of :data:`MOTIONS`; None where the capture lacks it (a capture without a held-out
    motion)."""
    cfg = ctx.cfg
    cap_dir, frames_dir, fit_dir, pbd_dir = (ctx.input_dir(s) for s in ("capture", "frames", "fit", "pbd"))
    if name == "reenact":
        reenact_dir = ctx.input_dir("reenact")
        report = json.loads((reenact_dir / "reenact_report.json").read_text())
        deform = read_table(reenact_dir / "deform.parquet", DEFORM)
        params = read_params(reenact_dir / "params.parquet")
        T = len(params["flame_global_orient"])
        offsets = np.asarray(deform["offsets"], dtype=np.float64).reshape(T, -1, 3)
        cameras = [
            {
                "id": view_name,
                "K": np.asarray(view["K"])[0].tolist(),
                "world_to_cam": np.asarray(view["world_to_cam"])[0].tolist(),
                **_image_size(reenact_dir / "frames" / view_name / "00000.png"),
            }
            for view_name, view in report["views"].items()
        ]
        driver = report["driver"]
        posed = posed_with_offsets(params, cfg, offsets)
        return Motion(
            "reenact",
            f"reenactment ({driver}, {report['sequence']})",
            posed,
            posed.conditioning(cfg),
            np.asarray(deform["contact"], dtype=bool),
            cameras,
            None,
            REENACT_BACKGROUND,
        )
    sequence = TRAIN_SEQUENCE if name == "train" else HELD_OUT_SEQUENCE
    if sequence not in CaptureIndex.read(cap_dir).sequences:
        ctx.metrics[f"{name}_skipped"] = f"the capture has no '{sequence}' sequence"
        return None
    posed = posed_sequence(
        fit_dir,
        sequence,
        cfg,
        applied_deformation(cfg, pbd_dir),
        method_params(ctx.input_dir("dynamic"), fit_dir, sequence),
    )
    T = posed.meshes.vertices.shape[0]
    split_views = [load_views(cap_dir, frames_dir, sequence, split) for split in _splits(frames_dir, sequence)]
    cameras = [
        {
            "id": views.camera_ids[c],
            "K": views.K[c].tolist(),
            "world_to_cam": views.world_to_cam[c].tolist(),
            "width": views.size,
            "height": views.size,
        }
        for views in split_views
        for c in range(views.num_cameras)
    ]
    images = np.concatenate([v.images.numpy() for v in split_views], axis=1)
    label = "training motion" if name == "train" else "held-out motion"
    background = split_views[0].background.tolist()
    contact = contact_flags(pbd_dir, sequence, T)
    return Motion(name, label, posed, posed.conditioning(cfg), contact, cameras, images, background)


def _image_size(path: Path) -> dict[str, int]:
    """{"width", "height"} of the image at ``path``."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"{path}: cannot read it; rerun the reenact stage")
    return {"width": int(image.shape[1]), "height": int(image.shape[0])}


def _splits(frames_dir: Path, sequence: str) -> list[str]:
    """The camera splits (train, test) with crops of ``sequence``."""
    index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    present = {split for seq, split in zip(index["sequence"], index["split"]) if seq == sequence}
    return [split for split in ("train", "test") if split in present]
