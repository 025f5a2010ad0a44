"""The browser viewer's folder (stage ``viewer``): the page, its bundle and the avatar's data, written from a trained
avatar and the motions it plays (:func:`write_viewer`). Not a stage: the stage gathers the motions from its inputs;
tests write a page from motions of their own."""

from __future__ import annotations

import logging
import shutil
from base64 import b64encode
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from avatar.artifacts.motion import PosedSequence
from avatar.device import host
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.representations import TrainedAvatar
from avatar.viewer.codec import (
    POSITION_LEVELS,
    STEPS,
    CodecConfig,
    FrameGaussians,
    Overrides,
    Ranges,
    StaticGaussians,
    apply_overrides,
    bit_mask,
    dequantise_vertices,
    differences_in_time,
    encode_overrides,
    frame_errors,
    pack_sections,
    pose_static,
    quantise_vertices,
    static_gaussians,
)
from data_schemas.web_escape import script_json, url_path
from data_schemas.writes import write_json

#: the page's source: index.html and the bundle ``make viewer`` builds (``npm ci && npm run build`` in viewer/)
PAGE_DIR = Path(__file__).resolve().parents[2] / "viewer"
BUNDLE = PAGE_DIR / "dist" / "viewer.js"
BUILD_COMMAND = "make viewer"
log = logging.getLogger(__name__)

#: a progress bar over a motion's frames: (frames, description) -> the frames
Progress = Callable[[Iterable[FrameGaussians], str], Iterator[FrameGaussians]]


@dataclass
class PageSettings:
    """How the page is written (``stage.viewer``'s settings but the motions)."""

    reference_frames: int = 16
    ground_truth: bool = True
    jpeg_quality: int = 90
    fps: float = 10.0


@dataclass
class Motion:
    """A motion the page plays: its name, menu label, posed sequence and the avatar's conditioning of its frames,
    contact flags (T,), the cameras it can be
    seen from (id, K, world_to_cam, width, height), their ground-truth crops (T, C, S, S, 3) u8 or None, and the
    background colour the project renders it on (3,)."""

    name: str
    label: str
    posed: PosedSequence
    cond: SequenceConditioning
    contact: np.ndarray
    cameras: list[dict]
    ground_truth: np.ndarray | None
    background: list[float]


def write_viewer(
    out_dir: Path,
    avatar: TrainedAvatar,
    motions: list[Motion],
    codec: CodecConfig,
    settings: PageSettings,
    identity: dict[str, str],
    progress: Progress = lambda frames, _: iter(frames),
) -> dict:
    """Write the viewer of ``avatar`` playing ``motions`` into ``out_dir``: ``index.html``, ``viewer.js`` (where the
    bundle is built), ``data/`` and ``viewer.json``, whose content it returns. ``identity`` (method, label,
    subject) goes into the page's manifest."""
    data_dir = out_dir / "data"
    data_dir.mkdir()
    faces = motions[0].posed.meshes.faces.numpy()
    face_part = motions[0].posed.meshes.face_part.numpy()
    triangle = host(avatar.triangles)
    posed_frames = {m.name: _pose_all(avatar, m) for m in motions}
    static = static_gaussians(
        _reference_samples(motions, posed_frames, settings.reference_frames), faces, face_part, triangle
    )
    avatar_bytes = _write_script(
        data_dir / "avatar.js",
        "window.IAV.avatar",
        {"faces": faces.astype(np.uint32), **vars(static)},
    )
    summaries = []
    for motion in motions:
        summaries.append(
            _write_motion(out_dir, motion, static, posed_frames.pop(motion.name), faces, codec, settings, progress)
        )
    parts = list(motions[0].posed.meshes.part_names)
    vertices = motions[0].posed.meshes.vertices[0].numpy()
    manifest = {
        **identity,
        "parts": parts,
        "background": motions[0].background,
        "centre": vertices.mean(0).tolist(),
        "gaussians": int(triangle.shape[0]),
        "steps": STEPS,
        "vertex_levels": POSITION_LEVELS,
        "avatar": {"file": "data/avatar.js", "bytes": avatar_bytes},
        "motions": [s["page"] for s in summaries],
    }
    (data_dir / "manifest.js").write_text(
        f"window.IAV = window.IAV || {{}};\nwindow.IAV.manifest = {script_json(manifest)};\n"
    )
    shutil.copyfile(PAGE_DIR / "index.html", out_dir / "index.html")
    built = BUNDLE.is_file()
    if built:
        shutil.copyfile(BUNDLE, out_dir / "viewer.js")
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
    write_json(out_dir / "viewer.json", report, "the browser viewer's sizes and quantisation error")
    return report


def _pose_all(avatar: TrainedAvatar, motion: Motion) -> list[FrameGaussians]:
    """Every frame of ``motion`` as the avatar poses it (as evaluated: no sampling noise). A frame whose mesh or
    Gaussians are not finite is refused, naming it (nothing is written). Posed on the avatar's device."""
    device = avatar.triangles.device
    vertices, cond = motion.posed.meshes.vertices.to(device), motion.cond.to(device)
    frames = []
    with torch.no_grad():
        for t in range(vertices.shape[0]):
            frame = FrameGaussians.of(avatar.pose(cond, vertices[t], t))
            bad = frame.non_finite()
            if bad or not torch.isfinite(vertices[t]).all():
                raise ValueError(
                    f"viewer: frame {t} of motion '{motion.name}' has non-finite {', '.join(bad) or 'vertices'}; "
                    "the trained model or its tracking is broken there (rerun the stage that made it)"
                )
            frames.append(frame)
    return frames


def _write_motion(
    out_dir: Path,
    motion: Motion,
    static: StaticGaussians,
    frames: list[FrameGaussians],
    faces: np.ndarray,
    codec: CodecConfig,
    settings: PageSettings,
    progress: Progress,
) -> dict:
    """Write ``data/motion-<name>.js`` (the quantised vertices and the overrides of every frame) and the
    ground-truth crops; returns its summary for viewer.json and its entry of the page's manifest (``page``: the
    script's URL percent-encoded, as the page loads it)."""
    vertices = motion.posed.meshes.vertices.double().numpy()
    ranges = Ranges.of(vertices)
    quantised = quantise_vertices(vertices, ranges)
    overrides: list[Overrides] = []
    errors: list[dict[str, float]] = []
    for t, frame in enumerate(progress(frames, f"viewer {motion.name}")):
        posed_static = pose_static(static, dequantise_vertices(quantised[t], ranges), faces)
        overrides.append(encode_overrides(frame, posed_static, codec))
        errors.append(frame_errors(apply_overrides(posed_static, overrides[-1]), frame))  # what the page draws
    N = static.triangle.shape[0]
    geometry = np.array([len(o.geometry) for o in overrides], dtype=np.uint32)
    appearance = np.array([len(o.appearance) for o in overrides], dtype=np.uint32)
    file = f"motion-{motion.name}.js"
    size = _write_script(
        out_dir / "data" / file,
        f"window.IAV.motions[{script_json(motion.name)}]",
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
    cameras = [dict(c, ground_truth=motion.ground_truth is not None and settings.ground_truth) for c in motion.cameras]
    if motion.ground_truth is not None and settings.ground_truth:
        for c, camera in enumerate(cameras):
            folder = out_dir / "data" / "gt" / motion.name / camera["id"]
            folder.mkdir(parents=True)
            for t in range(motion.ground_truth.shape[0]):
                image = cv2.cvtColor(motion.ground_truth[t, c], cv2.COLOR_RGB2BGR)
                cv2.imwrite(str(folder / f"{t:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, settings.jpeg_quality])
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
            "file": url_path("data", file),
            "frames": T,
            "fps": settings.fps,
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
    """Write ``arrays`` packed (:func:`avatar.viewer.codec.pack_sections`) as a script assigning them to
    ``target`` (a JavaScript expression, its names escaped by the caller); returns the file's size in bytes."""
    buffer, sections = pack_sections(arrays)
    text = (
        "window.IAV = window.IAV || {};\nwindow.IAV.motions = window.IAV.motions || {};\n"
        f'{target} = {{sections: {script_json(sections)}, data: "{b64encode(buffer).decode()}"}};\n'
    )
    path.write_text(text)
    return path.stat().st_size
