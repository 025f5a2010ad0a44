"""Stage ``viewer``: a page that plays the method's avatar in 3D in the browser (Spark on three.js).

It writes ``methods/<method>/viewer/``: ``index.html`` and ``viewer.js`` (the bundle ``make viewer`` builds from
``viewer/``), and ``data/``: the avatar's Gaussians once and, per motion, the posed vertices of every frame and the
Gaussians the frame changes beyond the codec's tolerances (:mod:`avatar.viewer_codec`), as scripts the page loads
from ``file://`` as well as from ``interactavatar-view``; the ground-truth crops of the capture cameras as JPEG;
``viewer.json``: sizes per frame and the quantisation error.
"""

from __future__ import annotations

import json
import logging
import shutil
from base64 import b64encode
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import DictConfig

from avatar.viewer_codec import (
    STEPS,
    CodecConfig,
    FrameGaussians,
    Overrides,
    Ranges,
    StaticGaussians,
    bit_mask,
    decode_frame,
    dequantise_vertices,
    differences_in_time,
    encode_overrides,
    frame_errors,
    pack_sections,
    pose_static,
    quantise_vertices,
    static_gaussians,
)
from data_schemas.capture import CaptureIndex
from data_schemas.deform import DEFORM
from data_schemas.frames import FRAMES_INDEX
from data_schemas.tables import SchemaError, read_table
from data_schemas.writes import write_json
from pipeline.schema import core_config, section_schema
from pipeline.sources import SourceFiles
from pipeline.stage import StageContext, stage
from stages.artifacts import TRAIN_SEQUENCE, contact_flags, load_views, method_params, read_params
from stages.dependencies import model_files
from stages.posing import PosedSequence, applied_deformation, posed_sequence, posed_with_offsets
from stages.representations import TrainedAvatar, load_trained

#: the page's source: index.html and the bundle ``make viewer`` builds (``npm ci && npm run build`` in viewer/)
PAGE_DIR = Path(__file__).resolve().parent.parent / "viewer"
BUNDLE = PAGE_DIR / "dist" / "viewer.js"
BUILD_COMMAND = "make viewer"
#: the motions the viewer can offer, in its menu's order: the training motion, the held-out one, the reenactment
MOTIONS = ("train", "test", "reenact")
HELD_OUT = "test"
log = logging.getLogger(__name__)


@dataclass
class ViewerSettings:
    """The stage's own settings (values in conf/stage/viewer.yaml)."""

    motions: list[str]
    reference_frames: int
    ground_truth: bool
    jpeg_quality: int
    fps: float


ViewerConfig = section_schema("ViewerConfig", CodecConfig, own=ViewerSettings)


def page_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # the SourceLister signature
    """The page's files (a rebuilt bundle reruns the stage) and the official model files (posing)."""
    page = [p for p in (PAGE_DIR / "index.html", BUNDLE) if p.is_file()]
    return SourceFiles(Path("/"), tuple(page + model_files(cfg)))


def viewer_checks(cfg: DictConfig) -> list[str]:
    """The settings of ``stage.viewer`` out of range."""
    conf = cfg.stage.viewer
    problems = [f"stage.viewer.{p}" for p in core_config(CodecConfig, conf).problems()]
    unknown = [m for m in conf.motions if m not in MOTIONS]
    if unknown or not conf.motions:
        problems.append(f"stage.viewer.motions={list(conf.motions)}: choose one or more of {list(MOTIONS)}")
    if int(conf.reference_frames) < 1:
        problems.append(f"stage.viewer.reference_frames={conf.reference_frames}: must be >= 1")
    return problems


@dataclass
class Motion:
    """A motion the page plays: its name, menu label, posed sequence, contact flags (T,), the cameras it can be
    seen from (id, K, world_to_cam, width, height), their ground-truth crops (T, C, S, S, 3) u8 or None, and the
    background colour the project renders it on (3,)."""

    name: str
    label: str
    posed: PosedSequence
    contact: np.ndarray
    cameras: list[dict]
    ground_truth: np.ndarray | None
    background: list[float]


@stage(
    "viewer",
    inputs=("capture", "frames", "fit", "pbd", "dynamic", "reenact"),
    config_keys=("model", "method", "stage.viewer"),
    outputs=("index.html", "data", "viewer.json"),
    version="1",
    config_schema=ViewerConfig,
    sources=page_sources,
    checks=viewer_checks,
    per_method=True,
)
def viewer(ctx: StageContext) -> None:
    """Write the browser viewer of the method's avatar: the page, its data per motion and frame, sizes and the
    quantisation error (viewer.json)."""
    conf = ctx.cfg.stage.viewer
    codec = core_config(CodecConfig, conf)
    model = load_trained(ctx.input_dir("dynamic"))
    motions = [m for m in (_motion(ctx, name) for name in conf.motions) if m is not None]
    if not motions:
        raise SchemaError(
            f"stage.viewer.motions={list(conf.motions)}: the capture has none of them; add reenact to play the "
            "reenactment"
        )
    data_dir = ctx.out_dir / "data"
    (data_dir / "gt").mkdir(parents=True)
    faces = motions[0].posed.meshes.faces.numpy()
    face_part = motions[0].posed.meshes.face_part.numpy()
    triangle = model.triangles.numpy()
    posed_frames = {m.name: _pose_all(model, m.posed, ctx.cfg) for m in motions}
    static = static_gaussians(
        _reference_samples(motions, posed_frames, int(conf.reference_frames)), faces, face_part, triangle
    )
    avatar_bytes = _write_script(
        data_dir / "avatar.js",
        "window.IAV.avatar",
        {"faces": faces.astype(np.uint32), **{k: v for k, v in vars(static).items()}},
    )
    summaries = []
    for motion in motions:
        summaries.append(_write_motion(ctx, motion, static, posed_frames.pop(motion.name), faces, codec, conf))
    parts = list(motions[0].posed.meshes.part_names)
    vertices = motions[0].posed.meshes.vertices[0].numpy()
    manifest = {
        "method": str(ctx.cfg.method.name),
        "label": str(ctx.cfg.method.label),
        "subject": ctx.subject,
        "parts": parts,
        "background": motions[0].background,
        "centre": vertices.mean(0).tolist(),
        "gaussians": int(triangle.shape[0]),
        "steps": STEPS,
        "avatar": {"file": "data/avatar.js", "bytes": avatar_bytes},
        "motions": [s["page"] for s in summaries],
    }
    (data_dir / "manifest.js").write_text(
        f"window.IAV = window.IAV || {{}};\nwindow.IAV.manifest = {json.dumps(manifest)};\n"
    )
    shutil.copyfile(PAGE_DIR / "index.html", ctx.out_dir / "index.html")
    built = BUNDLE.is_file()
    if built:
        shutil.copyfile(BUNDLE, ctx.out_dir / "viewer.js")
    else:
        log.warning(
            "viewer: the page's bundle %s is not built; the data is written. Build it: %s", BUNDLE, BUILD_COMMAND
        )
    frames = sum(s["frames"] for s in summaries)
    motion_bytes = sum(s["bytes"] for s in summaries)
    per_frame = motion_bytes / frames
    report = {
        "page_built": built,
        "build_command": BUILD_COMMAND,
        "gaussians": int(triangle.shape[0]),
        "avatar_bytes": avatar_bytes,
        "bytes_per_frame": per_frame,
        "mb_per_100_frames": (avatar_bytes + 100 * per_frame) / 1e6,
        "note": "sizes on disk (base64 in .js files, so the page works from file://); mb_per_100_frames: the "
        "avatar once plus 100 frames at the mean size per frame; errors: the decoded frame against the model's "
        "(geometry: the largest of the mean's distance, an axis' change and the rotation's angle times the "
        "axes' spread, mm; the mean's distance alone, mm; colour and opacity in 8-bit levels), before Spark's own "
        "packing (float16 centres, 8-bit log-scales, colours and opacities)",
        "motions": [{k: v for k, v in s.items() if k != "page"} for s in summaries],
    }
    write_json(ctx.out_dir / "viewer.json", report, "the browser viewer's sizes and quantisation error")
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
                f"{key}": max(s["errors"][key] for s in summaries)
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
        return Motion(
            "reenact",
            f"reenactment ({driver}, {report['sequence']})",
            posed_with_offsets(params, cfg, offsets),
            np.asarray(deform["contact"], dtype=bool),
            cameras,
            None,
            [float(c) for c in report.get("background", (1.0, 1.0, 1.0))],
        )
    sequence = TRAIN_SEQUENCE if name == "train" else HELD_OUT
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
    return Motion(name, label, posed, contact_flags(pbd_dir, sequence, T), cameras, images, background)


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


def _pose_all(model: TrainedAvatar, posed: PosedSequence, cfg: DictConfig) -> list[FrameGaussians]:
    """Every frame of ``posed`` as the model poses it (as evaluated: no sampling noise)."""
    cond = posed.conditioning(cfg)
    with torch.no_grad():
        return [
            FrameGaussians.of(model.pose(cond, posed.meshes.vertices[t], t))
            for t in range(posed.meshes.vertices.shape[0])
        ]


def _write_motion(
    ctx: StageContext,
    motion: Motion,
    static: StaticGaussians,
    frames: list[FrameGaussians],
    faces: np.ndarray,
    codec: CodecConfig,
    conf: DictConfig,
) -> dict:
    """Write ``data/motion-<name>.js`` (the quantised vertices and the overrides of every frame) and the
    ground-truth crops; returns its summary for viewer.json and its entry of the page's manifest (``page``)."""
    vertices = motion.posed.meshes.vertices.double().numpy()
    ranges = Ranges.of(vertices)
    quantised = quantise_vertices(vertices, ranges)
    overrides: list[Overrides] = []
    errors: list[dict[str, float]] = []
    for t, frame in enumerate(ctx.progress(frames, desc=f"viewer {motion.name}")):
        posed_static = pose_static(static, dequantise_vertices(quantised[t], ranges), faces)
        overrides.append(encode_overrides(frame, posed_static, codec))
        errors.append(frame_errors(decode_frame(static, quantised[t], overrides[-1], ranges, faces), frame))
    N = static.triangle.shape[0]
    geometry = np.array([len(o.geometry) for o in overrides], dtype=np.uint32)
    appearance = np.array([len(o.appearance) for o in overrides], dtype=np.uint32)
    file = f"data/motion-{motion.name}.js"
    size = _write_script(
        ctx.out_dir / file,
        f"window.IAV.motions.{motion.name}",
        {
            "vertices": differences_in_time(quantised),
            "geometry_mask": np.stack([bit_mask(o.geometry, N) for o in overrides]),
            "geometry_start": (np.cumsum(geometry) - geometry).astype(np.uint32),
            "appearance_mask": np.stack([bit_mask(o.appearance, N) for o in overrides]),
            "appearance_start": (np.cumsum(appearance) - appearance).astype(np.uint32),
            **{
                name: np.concatenate([getattr(o, name) for o in overrides])
                for name in ("d_mean", "d_log_scale", "d_rotation", "d_rgba")
            },
        },
    )
    cameras = [
        dict(c, ground_truth=motion.ground_truth is not None and bool(conf.ground_truth)) for c in motion.cameras
    ]
    if motion.ground_truth is not None and conf.ground_truth:
        for c, camera in enumerate(cameras):
            folder = ctx.out_dir / "data" / "gt" / motion.name / camera["id"]
            folder.mkdir(parents=True)
            for t in range(motion.ground_truth.shape[0]):
                image = cv2.cvtColor(motion.ground_truth[t, c], cv2.COLOR_RGB2BGR)
                cv2.imwrite(str(folder / f"{t:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, int(conf.jpeg_quality)])
    T = len(frames)
    worst = {k: max(e[k] for e in errors) for k in errors[0] if k.endswith("_max")}
    mean = {k: float(np.mean([e[k] for e in errors])) for k in errors[0] if k.endswith("_mean")}
    return {
        "name": motion.name,
        "frames": T,
        "bytes": size,
        "bytes_per_frame": size / T,
        "geometry_overrides_per_frame": float(geometry.mean()),
        "appearance_overrides_per_frame": float(appearance.mean()),
        "errors": {**worst, **mean},
        "page": {
            "name": motion.name,
            "label": motion.label,
            "file": file,
            "frames": T,
            "fps": float(conf.fps),
            "contact": motion.contact.astype(int).tolist(),
            "ranges": ranges.to_json(),
            "cameras": cameras,
        },
    }


def _reference_samples(
    motions: list[Motion], posed_frames: dict[str, list[FrameGaussians]], count: int
) -> list[tuple[FrameGaussians, np.ndarray]]:
    """``count`` frames spread evenly over all motions: (the model's Gaussians, the vertices (V, 3))."""
    pairs = [(m.name, t) for m in motions for t in range(len(posed_frames[m.name]))]
    vertices = {m.name: m.posed.meshes.vertices for m in motions}
    chosen = np.unique(np.linspace(0, len(pairs) - 1, min(count, len(pairs))).round().astype(int))
    return [(posed_frames[n][t], vertices[n][t].double().numpy()) for n, t in (pairs[i] for i in chosen)]


def _write_script(path: Path, target: str, arrays: dict[str, np.ndarray]) -> int:
    """Write ``arrays`` packed (:func:`avatar.viewer_codec.pack_sections`) as a script assigning them to
    ``target``; returns the file's size in bytes."""
    buffer, sections = pack_sections(arrays)
    text = (
        "window.IAV = window.IAV || {};\nwindow.IAV.motions = window.IAV.motions || {};\n"
        f'{target} = {{sections: {json.dumps(sections)}, data: "{b64encode(buffer).decode()}"}};\n'
    )
    path.write_text(text)
    return path.stat().st_size
