"""Stage ``reenact``: drive the method's trained avatar with a parameter sequence and make it watchable.

``reenact.driver``: ``self`` (the subject's own held-out ``reenact.sequence``, normally ``test``), another
subject of the same outputs folder (its ``fit`` of that sequence becomes an input: re-fitting the driver
reruns this stage) or a ``params.parquet`` file (its content digest enters the cache key). Another actor's
motion is transferred onto the target (:func:`avatar.reenact.transfer_motion`: the target keeps its shape
and place, the hand keeps the driver's hand-to-head transform scaled by the head sizes); then contact is
simulated on the target's face with the pbd stage's solver and settings (when the method uses PBD) and the
model renders every frame, its interaction module on the simulated offsets.

Writes ``videos/<camera_id>.mp4`` (the chosen capture cameras, cropped to the performance) and
``videos/orbit.mp4`` (one turn around the head over the sequence), H.264 MP4 that plays in a browser; where
the capture holds this identity performing the driving motion (``self``: the held-out sequence; another
subject: the synthetic ``cross_<driver>`` sequence), also ``videos/<camera_id>_gt.mp4`` (that ground truth
through the same crop) and ``videos/<camera_id>_vs_gt.mp4`` (reenacted | ground truth, always in step);
``frames/<view>/<frame>.png``; ``ply/<frame>.ply`` (world-space 3DGS, any splat viewer);
``params.parquet`` (the driving parameters as applied), ``deform.parquet`` (the simulated offsets) and
``reenact_report.json`` (driver, head-size ratio, per-frame residual penetration, render timings).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import (
    HELD_OUT_SEQUENCE,
    TRAIN_SEQUENCE,
    load_params,
    load_scene,
    method_params,
    write_frame_ply,
)
from avatar.artifacts.dependencies import contact_sources, unused_driving_settings
from avatar.device import host
from avatar.reenact.cameras import framed_intrinsics, orbit, orbit_intrinsics, reframe
from avatar.reenact.driving import (
    DRIVER_CHOICES,
    drive,
    driver_file_problem,
    driver_subject,
    is_parameter_file,
    placement_problem,
    transfer_summary,
    transferred_params,
)
from avatar.render.gaussians import render_gaussians, resolve_backend
from avatar.representations import load_trained
from avatar.templates.lbs import batch_rodrigues
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, cross_sequence, mask_path, video_path
from data_schemas.deform import DEFORM
from data_schemas.images import read_png, to_uint8, write_png
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.sources import SourceFiles
from data_schemas.tables import SchemaError, read_table, write_table
from data_schemas.video import iter_video
from data_schemas.web_video import write_web_video
from data_schemas.writes import write_json
from pipeline.config import synthetic_camera_ids
from pipeline.stage import StageContext, stage


@dataclass
class ReenactConfig:
    """Types of ``stage.reenact`` (values in conf/stage/reenact.yaml)."""

    cameras: list[str]
    orbit: bool
    margin: float
    image_size: int
    background: list[float]
    fps: float
    ply: bool
    backend: str


def _sources(cfg: DictConfig, subject: str) -> SourceFiles:
    """The contact model's files, and the driver's parameter file when ``reenact.driver`` names one."""
    files = contact_sources(cfg, subject)
    driver = str(cfg.reenact.driver)
    if not is_parameter_file(driver):
        return files
    path = Path(driver).resolve()
    if not path.is_file():
        raise SchemaError(f"reenact.driver={driver}: no such file; {DRIVER_CHOICES}")
    return SourceFiles(Path("/"), (*files.files, path))


def reenact_checks(cfg: DictConfig) -> list[str]:
    """What the reenactment cannot run with, found before any stage runs (not after training): an unknown
    ``reenact.placement``, a driver file that is not a params table, and ``stage.reenact.cameras`` the capture
    does not have where its camera ids are known now (:func:`capture_camera_ids`)."""
    driver = str(cfg.reenact.driver)
    problems = (
        placement_problem(cfg),
        driver_file_problem(driver) if is_parameter_file(driver) else None,
        cameras_problem(cfg),
    )
    return [p for p in problems if p is not None]


def cameras_problem(cfg: DictConfig) -> str | None:
    """Why ``stage.reenact.cameras`` names cameras the capture does not have, or ``None`` (also where the
    capture's camera ids are not known before it runs: the capture stage names them)."""
    wanted = [str(c) for c in cfg.stage.reenact.cameras]
    ids = capture_camera_ids(cfg) if wanted else None
    unknown = [c for c in wanted if ids is not None and c not in ids]
    if not unknown:
        return None
    return (
        f"stage.reenact.cameras={wanted}: {unknown} not among the capture's cameras {ids}; choose among them, or "
        "[] for the held-out camera(s) and the first train camera"
    )


def capture_camera_ids(cfg: DictConfig) -> list[str] | None:
    """The camera ids the capture will have, where they are known before it runs: the synthetic rig's, and a
    capture folder's (the names of its sequences' videos or image folders, which the capture stage requires to
    be its calibration's cameras); ``None`` otherwise (a folder not there yet or not readable, DECAF)."""
    dataset = cfg.dataset
    if dataset.name == "synthetic":
        return synthetic_camera_ids(cfg)
    if dataset.name != "folder":
        return None
    from importers.folder import view_sources  # COLMAP, nerfstudio: folder captures only

    src = Path(str(dataset.root)) / str(cfg.subject)
    try:
        ids = {camera for seq in sorted(src.iterdir()) if seq.is_dir() for camera in view_sources(seq)}
    except (OSError, SchemaError):  # no folder, or one the capture stage will name
        return None
    return sorted(ids) or None


@stage(
    "reenact",
    inputs=("capture", "fit", "scene", "dynamic"),
    config_keys=("model", "method", "reenact", "stage.reenact", "stage.pbd.solver", "quality.image_size"),
    outputs=("videos", "frames", "ply", "params.parquet", "deform.parquet", "reenact_report.json"),
    version="8",
    device=True,
    precision=True,
    config_schema=ReenactConfig,
    per_method=True,
    subject_inputs=("fit",),
    input_subject=driver_subject,
    sources=_sources,
    unused_keys=unused_driving_settings,
    checks=reenact_checks,
)
def reenact(ctx: StageContext) -> None:
    """Drive the method's avatar with reenact.driver; videos, frames, PLY sequence, contact report."""
    conf, cfg = ctx.cfg.stage.reenact, ctx.cfg
    sequence, sequence_note = (
        self_sequence(ctx.input_dir("capture"), str(cfg.reenact.sequence))
        if str(cfg.reenact.driver) == "self"
        else (str(cfg.reenact.sequence), "")
    )
    params, driver_label, scale, transfer_frames = _driving_params(ctx, sequence)
    driven = drive(cfg, params, load_scene(ctx.input_dir("scene")), scale)
    meshes, cond, offsets, pbd_frames = driven.meshes, driven.cond, driven.offsets, driven.pbd_frames
    T = offsets.shape[0]
    model = load_trained(ctx.input_dir("dynamic")).on_device(ctx.device, ctx.precision)
    size = int(conf.image_size) or int(cfg.quality.image_size)
    views = _views(ctx, meshes.vertices.numpy().reshape(-1, 3), params, size)
    meshes, cond = meshes.to(ctx.device), cond.to(ctx.device)
    background = torch.tensor(list(conf.background), dtype=torch.float32)
    rendered: dict[str, list[np.ndarray]] = {name: [] for name in views}
    model_s, render_s = 0.0, 0.0
    if conf.ply:
        (ctx.out_dir / "ply").mkdir()
    for t in ctx.progress(range(T), desc="reenact", total=T):
        with torch.no_grad():
            start = time.perf_counter()
            g = model.pose(cond, meshes.vertices[t], t)
            model_s += time.perf_counter() - start
            for name, (K, w2c) in views.items():
                start = time.perf_counter()
                out = render_gaussians(
                    g.means,
                    g.quats,
                    g.scales,
                    g.opacities,
                    g.colors,
                    torch.tensor(K[t], dtype=torch.float32, device=ctx.device),
                    torch.tensor(w2c[t], dtype=torch.float32, device=ctx.device),
                    size,
                    size,
                    background.to(ctx.device),
                    backend=conf.backend,
                )
                render_s += time.perf_counter() - start
                rendered[name].append(to_uint8(host(out.rgb)))
            if conf.ply:
                write_frame_ply(ctx.out_dir / "ply" / f"{t:05d}.ply", g)
    fps = float(conf.fps) or _capture_fps(ctx.input_dir("capture"))
    for name, images in rendered.items():
        write_web_video(ctx.out_dir / "videos" / f"{name}.mp4", images, fps)
        for t, image in enumerate(images):
            write_png(ctx.out_dir / "frames" / name / f"{t:05d}.png", image)
    if not conf.ply:
        (ctx.out_dir / "ply").mkdir()
    truth_sequence, truth_note = _ground_truth_sequence(ctx, T, sequence)
    truth_cameras = [] if truth_sequence is None else [name for name in views if name != "orbit"]
    capture_K = {c.camera_id: c.K for c in read_cameras(ctx.input_dir("capture") / "cameras.parquet")}
    for name in truth_cameras:
        assert truth_sequence is not None  # there are truth cameras only with a ground-truth sequence
        truth = _write_ground_truth(ctx, truth_sequence, name, capture_K[name], views[name][0], size, background, fps)
        write_web_video(
            ctx.out_dir / "videos" / f"{name}_vs_gt.mp4",
            (np.concatenate([ours, gt], axis=1) for ours, gt in zip(rendered[name], truth)),
            fps,
        )
    write_table(ctx.out_dir / "params.parquet", PARAMS, {"frame": np.arange(T), **params})
    contact = np.abs(offsets).reshape(T, -1).max(axis=1) > 0
    write_table(
        ctx.out_dir / "deform.parquet",
        DEFORM,
        {"frame": np.arange(T), "contact": contact, "offsets": offsets.reshape(T, -1)},
    )
    timings = {
        "model_ms_per_frame": 1000 * model_s / T,
        "render_ms_per_view": 1000 * render_s / (T * len(views)),
        "image_size": size,
    }
    timings["frames_per_second"] = 1000 / (timings["model_ms_per_frame"] + timings["render_ms_per_view"])
    simulated = [f for f in pbd_frames if f["simulated"]]
    write_json(
        ctx.out_dir / "reenact_report.json",
        {
            "driver": driver_label,
            "sequence": sequence,
            "sequence_note": sequence_note,
            "frames": T,
            "head_scale": scale,
            "views": {name: {"K": K.tolist(), "world_to_cam": w2c.tolist()} for name, (K, w2c) in views.items()},
            "views_note": "per frame: K (T, 3, 3) and world_to_cam (T, 4, 4)",
            "pbd": {"simulated": bool(cfg.method.pbd), "stiffness": driven.stiffness_source, "frames": pbd_frames},
            "ground_truth": {"sequence": truth_sequence, "cameras": truth_cameras, "note": truth_note},
            "transfer": {
                "placement": "none" if str(cfg.reenact.driver) == "self" else str(cfg.reenact.placement),
                "frames": transfer_frames,
            },
            "video_fps": fps,
        },
        "reenactment report",
    )
    ctx.metrics.update(
        {
            "frames": T,
            "views": len(views),
            "head_scale": scale,
            "contact_frames": int(contact.sum()),
            "simulated_frames": len(simulated),
            "ground_truth_videos": len(truth_cameras),
            "penetration_max_mm": max((f["penetration_max_mm"] for f in simulated), default=0.0),
            **timings,
            "rasterizer": resolve_backend(conf.backend, meshes.vertices),
            **transfer_summary(transfer_frames),
        }
    )


def self_sequence(capture_dir: Path, requested: str) -> tuple[str, str]:
    """(the sequence ``reenact.driver=self`` drives the avatar with, why). The requested one, except that a
    capture without the held-out ``test`` sequence (optional for a folder capture) reenacts its training motion
    instead of failing at the end of the DAG; any other sequence the capture lacks stays an error (listed)."""
    sequences = CaptureIndex.read(capture_dir).sequences
    if requested == HELD_OUT_SEQUENCE and HELD_OUT_SEQUENCE not in sequences and TRAIN_SEQUENCE in sequences:
        return TRAIN_SEQUENCE, (
            f"the capture has no held-out '{HELD_OUT_SEQUENCE}' sequence: the avatar reenacts the "
            f"training motion '{TRAIN_SEQUENCE}' instead (add <capture>/{HELD_OUT_SEQUENCE}/ for a "
            "held-out motion)"
        )
    return requested, ""


def _check_fitted(fit_dir: Path, sequence: str, whose: str) -> None:
    """One clear error when ``fit_dir`` has no fitted ``sequence``, listing the sequences it has."""
    if not (fit_dir / sequence / "params.parquet").is_file():
        there = sorted(p.parent.name for p in fit_dir.glob("*/params.parquet"))
        raise SchemaError(
            f"reenact.sequence={sequence}: {whose} has no fitted sequence '{sequence}' ({fit_dir}); "
            f"choose one of {there}"
        )


def _driving_params(ctx: StageContext, sequence: str) -> tuple[dict[str, np.ndarray], str, float, list[dict]]:
    """(parameters of every output frame on the target, where they came from, head-size ratio target / driver,
    the transfer's per-frame report of the hand's contacts: empty for ``self`` and ``reenact.placement=scaled``);
    ``sequence``: the driver's sequence (for ``self``, :func:`self_sequence`'s)."""
    driver = str(ctx.cfg.reenact.driver)
    if driver == "self":
        _check_fitted(ctx.input_dir("fit"), sequence, "this subject")
        # the train motion as the method refined it while training (the fit's for any other sequence)
        return method_params(ctx.input_dir("dynamic"), ctx.input_dir("fit"), sequence), f"self ({sequence})", 1.0, []
    if is_parameter_file(driver):
        path = Path(driver)
        table = read_table(path, PARAMS)
        params, label = {k: np.asarray(table[k]) for k in PARAM_COLUMNS}, str(path)
    else:
        path = ctx.subject_input_dir("fit") / sequence / "params.parquet"
        _check_fitted(ctx.subject_input_dir("fit"), sequence, f"the driver '{driver}'")
        params, label = load_params(ctx.subject_input_dir("fit"), sequence), f"{driver} ({sequence})"
    transfer = transferred_params(ctx.cfg, ctx.input_dir("fit"), params, path)
    return transfer.params, label, transfer.head_scale, transfer.frames


def _views(
    ctx: StageContext, points: np.ndarray, params: dict[str, np.ndarray], size: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (K (T, 3, 3), world_to_cam (T, 4, 4)) per frame: the chosen capture cameras, cropped to
    ``points`` (all frames' vertices), and the orbit around them (one turn over the T frames)."""
    conf = ctx.cfg.stage.reenact
    path = ctx.input_dir("capture") / "cameras.parquet"
    cameras = read_cameras(path)
    by_id = {c.camera_id: c for c in cameras}
    wanted = list(conf.cameras) or [c.camera_id for c in cameras if c.split == "test"] + [
        next(c.camera_id for c in cameras if c.split == "train")
    ]
    unknown = [c for c in wanted if c not in by_id]
    if unknown:
        raise SchemaError(f"stage.reenact.cameras: {unknown} are not cameras of {path}; choose among {sorted(by_id)}")
    T = len(params["flame_global_orient"])
    views = {}
    for camera_id in wanted:
        cam = by_id[camera_id]
        try:
            K = framed_intrinsics(cam.K, cam.world_to_cam, points, size, float(conf.margin))
        except ValueError as exc:
            raise SchemaError(f"stage.reenact.cameras: camera '{camera_id}' of {path}: {exc}") from exc
        views[camera_id] = (np.repeat(K[None], T, 0), np.repeat(cam.world_to_cam[None], T, 0))
    if conf.orbit:
        centre = points.mean(0)
        radius = float(np.linalg.norm(points - centre, axis=1).max()) * (1 + float(conf.margin))
        head_rotation = batch_rodrigues(torch.tensor(np.asarray(params["flame_global_orient"][:1], np.float64)))
        up = head_rotation[0].numpy()[:, 1]  # the head's up axis on the first frame
        eye = by_id[wanted[0]].cam_to_world[:3, 3]
        K = orbit_intrinsics(float(np.linalg.norm(eye - centre)), radius, size)
        views["orbit"] = (np.repeat(K[None], T, 0), np.stack(orbit(eye, centre, up, T)))
    return views


def _ground_truth_sequence(ctx: StageContext, num_frames: int, sequence: str) -> tuple[str | None, str]:
    """(the capture sequence that shows this identity performing the driving motion, or None; why).
    ``sequence``: the driver's (for ``self``, the capture sequence itself)."""
    driver = str(ctx.cfg.reenact.driver)
    if is_parameter_file(driver):
        return None, "driven by a parameter file: no capture of this identity performing it"
    if driver != "self":
        sequence = cross_sequence(driver)
    info = CaptureIndex.read(ctx.input_dir("capture")).sequences.get(sequence)
    if info is None:
        return (
            None,
            f"the capture has no sequence '{sequence}' (synthetic captures render it with "
            f"stage.capture.cross_reenactment=true)",
        )
    if info.num_frames != num_frames:
        return None, f"the capture's '{sequence}' has {info.num_frames} frames, the driving motion {num_frames}"
    return sequence, f"the capture's '{sequence}' through the same crops"


def _write_ground_truth(
    ctx: StageContext,
    sequence: str,
    camera_id: str,
    K_capture: np.ndarray,
    K: np.ndarray,
    size: int,
    background: torch.Tensor,
    fps: float,
) -> list[np.ndarray]:
    """Write ``videos/<camera_id>_gt.mp4``: the capture's ``sequence`` from camera ``camera_id`` reframed to
    the reenactment's per-frame intrinsics ``K`` (T, 3, 3) at ``size`` px from the camera's own ``K_capture``
    (3, 3), put on the reenactment's background where the capture has masks; return its frames (size, size, 3)
    uint8."""
    capture_dir = ctx.input_dir("capture")
    fill = background.numpy() * 255
    frames = []
    for t, image in enumerate(iter_video(video_path(capture_dir, sequence, camera_id))):
        truth = reframe(image, K_capture, K[t], size, tuple(fill.tolist())).astype(np.float32)
        mask = mask_path(capture_dir, sequence, camera_id, t)
        if mask.is_file():
            alpha = reframe((read_png(mask, 1) > 0).astype(np.float32), K_capture, K[t], size, (0.0, 0.0, 0.0))[
                ..., None
            ]  # one channel: OpenCV uses the first border value
            truth = truth * alpha + fill * (1 - alpha)
        frames.append((truth + 0.5).clip(0, 255).astype(np.uint8))
    write_web_video(ctx.out_dir / "videos" / f"{camera_id}_gt.mp4", frames, fps)
    return frames


def _capture_fps(capture_dir: Path) -> float:
    """The capture's frame rate (its first sequence's)."""
    return float(next(iter(CaptureIndex.read(capture_dir).sequences.values())).frame_rate)
