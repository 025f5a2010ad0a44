"""The frames of a motion posed as the pipeline poses them, and written as 3DGS PLY files with their record."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from avatar.artifacts import (
    TRAIN_SEQUENCE,
    PosedGaussians,
    load_params,
    load_scene,
    method_params,
    read_params,
    write_frame_ply,
)
from avatar.artifacts.motion import applied_deformation, load_sequence, templates
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.geometry.frames import quaternion_multiply, rotation_to_quaternion
from avatar.posing import MeshSequence, posed_meshes
from avatar.reenact import parameter_problem
from avatar.reenact.driving import drive, is_parameter_file, transferred_params
from avatar.render.gaussians import WorldGaussians
from avatar.representations import TrainedAvatar, load_trained
from avatar.templates.lbs import batch_rodrigues
from data_schemas.tables import SchemaError
from data_schemas.writes import write_json
from pipeline.export_ply.destination import EXPORT_INFO, check_destination, partial_folder, publish, write_problem
from pipeline.export_ply.options import AXES, PROG, ExportError
from pipeline.export_ply.trained import TrainedRun, open_run
from pipeline.manifest import MANIFEST_NAME, sha256_file

#: OpenGL's axes from OpenCV's and back: 180 degrees about x, (x, y, z) -> (x, -y, -z)
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def motion_params(run: TrainedRun, motion: str) -> dict[str, np.ndarray]:
    """The parameters of ``motion``: a motion of the fit (:meth:`TrainedRun.motions`; the training motion as the
    method refined it) or a params.parquet file (the driver's own, before the transfer onto the subject), refused
    where a value is not finite or beyond any capture (:func:`avatar.reenact.parameter_problem`)."""
    if not is_parameter_file(motion):
        if motion not in run.motions():
            raise ExportError(f"--motion {motion}: unknown motion; {_motion_choices(run)}")
        return method_params(run.dynamic_dir, run.fit_dir, motion)
    path = Path(motion)
    if not path.is_file():
        raise ExportError(f"--motion {motion}: no such file; {_motion_choices(run)}")
    try:
        params = read_params(path)
    except SchemaError as exc:
        raise ExportError(f"--motion {motion}: not a params table ({exc}); {_motion_choices(run)}") from exc
    problem = parameter_problem(params)
    if problem is not None:
        raise ExportError(f"--motion {motion}: {problem}")
    return params


def _motion_choices(run: TrainedRun) -> str:
    return f"give one of the fit's motions ({', '.join(run.motions())}) or a params.parquet file (the fit's schema)"


def posed_motion(
    run: TrainedRun, motion: str, params: dict[str, np.ndarray]
) -> tuple[MeshSequence, SequenceConditioning]:
    """The meshes and conditioning of every frame of ``motion`` (its ``params``: :func:`motion_params`), as the
    pipeline poses them: a motion of the fit as ``evaluate`` does (with the pbd stage's offsets where the method
    uses them), a driver file as ``reenact`` does (transferred onto the subject, its contact simulated)."""
    if is_parameter_file(motion):
        transfer = transferred_params(run.cfg, run.fit_dir, params, Path(motion))
        driven = drive(run.cfg, transfer.params, load_scene(run.subject_dir / "scene"), transfer.head_scale)
        return driven.meshes, driven.cond
    pbd_dir = applied_deformation(run.cfg, run.subject_dir / "pbd")
    return load_sequence(run.fit_dir, motion, run.cfg, pbd_dir=pbd_dir, params=params)


def parse_frames(spec: str, num_frames: int, motion: str) -> list[int]:
    """The frames ``--frames`` names: ``all``, or comma-separated frames and inclusive ranges (``0,5,10-19``), in
    order, each once; :class:`ExportError` for one outside 0..num_frames-1 (found before any range is spelled out)."""
    if spec.strip() == "all":
        return list(range(num_frames))
    ranges = [_frame_range(part.strip(), spec) for part in spec.split(",")]
    for lo, hi in ranges:
        if hi >= num_frames:
            raise ExportError(
                f"--frames {spec}: frame {max(lo, num_frames)} out of range; motion '{motion}' has frames "
                f"0..{num_frames - 1}"
            )
    return list(dict.fromkeys(t for lo, hi in ranges for t in range(lo, hi + 1)))


def _frame_range(part: str, spec: str) -> tuple[int, int]:
    """(first, last) of one frame (``5``) or inclusive range (``10-19``) of ``--frames spec``."""
    first, sep, last = part.partition("-")
    try:
        lo, hi = int(first), int(last) if sep else int(first)
    except ValueError:
        raise ExportError(
            f"--frames {spec}: expected 'all' or frames and ranges such as 0,5,10-19 (the first frame is 0)"
        ) from None
    if lo > hi:
        raise ExportError(f"--frames {spec}: range {part} runs backwards")
    return lo, hi


def axes_frame(run: TrainedRun, axes: str) -> tuple[np.ndarray, np.ndarray]:
    """(A (3, 3), c (3,)) of ``--axes``: a file holds A (p - c) for a world point p, and its rotations turned by A.
    ``world``: the identity; ``opengl``: A = R0^T and c = c0, the head's rotation and the centroid of its face mesh on
    the training motion's first frame as fitted; ``opencv``: A = diag(1, -1, -1) R0^T, c = c0."""
    if axes not in AXES:
        raise ExportError(f"--axes {axes}: choose one of {', '.join(AXES)}")
    if axes == "world":
        return np.eye(3), np.zeros(3)
    params = {k: v[:1] for k, v in load_params(run.fit_dir, TRAIN_SEQUENCE).items()}
    head_rotation = batch_rodrigues(torch.tensor(np.asarray(params["flame_global_orient"], np.float64)))[0].numpy()
    head, hand = templates(run.cfg.model)
    face = posed_meshes(params, head, hand).vertices[0, : head.num_vertices]  # the face's vertices come first
    rotation = head_rotation.T if axes == "opengl" else FLIP_YZ @ head_rotation.T
    return rotation, face.double().numpy().mean(0)


def in_axes(g: WorldGaussians, rotation: np.ndarray, centre: np.ndarray) -> PosedGaussians:
    """``g`` in the frame of :func:`axes_frame` (rotation A, centre c): means A (mu - c), quaternions q(A) q, made
    unit; scales, opacities and colours as they are. The identity leaves the means bit for bit."""
    quats = g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if np.array_equal(rotation, np.eye(3)) and not centre.any():
        return PosedGaussians(g.means, g.scales, quats, g.opacities, g.colors)
    A = torch.tensor(rotation, dtype=torch.float64, device=g.means.device)
    means = ((g.means.double() - torch.tensor(centre, device=g.means.device)) @ A.T).to(g.means.dtype)
    quats = quaternion_multiply(rotation_to_quaternion(A).to(quats.dtype)[None], quats)
    return PosedGaussians(means, g.scales, quats, g.opacities, g.colors)


def export_motion(
    run: TrainedRun,
    motion: str,
    out: Path,
    *,
    frames: str = "all",
    axes: str = "world",
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
    device: str = "cpu",
) -> list[Path]:
    """Write the frames ``frames`` (:func:`parse_frames`) of ``motion`` as ``out/<frame>.ply`` (five digits) and
    ``out/export.json``; return the PLY paths. The folder appears whole or not at all: the files are written into a
    hidden folder beside it that is renamed into place (replacing an earlier export only with ``overwrite``:
    :func:`pipeline.export_ply.destination.check_destination`). The avatar poses the frames on the torch ``device``,
    its networks in the precision its training ran them in. Call it inside :func:`open_run` (``run``'s locks held)."""
    check_destination(out, overwrite, run.subject_dir)
    params = motion_params(run, motion)
    chosen = parse_frames(frames, len(params["flame_global_orient"]), motion)
    rotation, centre = axes_frame(run, axes)
    try:
        meshes, cond = posed_motion(run, motion, params)
        model = load_trained(run.dynamic_dir).on_device(device, trained_precision(run.dynamic_dir))
    except SchemaError as exc:
        raise ExportError(str(exc)) from exc
    meshes, cond = meshes.to(device), cond.to(device)
    record = _record(run, motion, axes, rotation, centre, model)
    with partial_folder(out) as partial:
        try:
            names = _write_frames(partial, model, meshes, cond, chosen, rotation, centre, progress)
            write_json(partial / EXPORT_INFO, {**record, "frames": chosen, "files": names}, "the export's record")
            publish(partial, out)
        except OSError as exc:
            raise ExportError(write_problem(out, exc)) from exc
    return [out / name for name in names]


def _record(
    run: TrainedRun, motion: str, axes: str, rotation: np.ndarray, centre: np.ndarray, model: TrainedAvatar
) -> dict[str, Any]:
    """export.json but the frames and files: what was exported, from what (the output digest of every artifact read,
    a driver file's sha256), in which axes."""
    world_to_file = np.eye(4)
    world_to_file[:3, :3], world_to_file[:3, 3] = rotation, -rotation @ centre
    driver = {"motion_sha256": sha256_file(Path(motion))} if is_parameter_file(motion) else {}
    return {
        "tool": PROG,
        "subject": run.subject_dir.name,
        "run": run.run,
        "motion": motion,
        **driver,
        "read": run.read,
        "gaussians": model.num_gaussians,
        "axes": axes,
        "world_to_file": world_to_file.tolist(),
        "units": "metres",
    }


def trained_precision(dynamic_dir: Path) -> str:
    """The ``run.precision`` the dynamic stage in ``dynamic_dir`` ran its networks in (its manifest's ``device``;
    fp32 where it records none)."""
    manifest = json.loads((dynamic_dir / MANIFEST_NAME).read_text())
    return str((manifest.get("device") or {}).get("precision", "fp32"))


def _write_frames(
    folder: Path,
    model: TrainedAvatar,
    meshes: MeshSequence,
    cond: SequenceConditioning,
    frames: Sequence[int],
    rotation: np.ndarray,
    centre: np.ndarray,
    progress: Callable[[str], None] | None,
) -> list[str]:
    names = []
    for i, t in enumerate(frames):
        name = f"{t:05d}.ply"
        with torch.no_grad():
            write_frame_ply(folder / name, in_axes(model.pose(cond, meshes.vertices[t], t), rotation, centre))
        names.append(name)
        if progress is not None:
            progress(f"frame {t} ({i + 1}/{len(frames)}) -> {name}")
    return names


def export_frame(
    subject_dir: Path,
    sequence: str,
    frame: int,
    out: Path,
    method: str = "interactavatar",
    seed: int = 0,
) -> None:
    """Write frame ``frame`` of ``sequence`` (a motion of the fit or a params.parquet) of the trained ``method``
    under ``subject_dir`` to the single file ``out``, in world axes."""
    with open_run(subject_dir, method, seed) as run:
        params = motion_params(run, sequence)
        (t,) = parse_frames(str(frame), len(params["flame_global_orient"]), sequence)
        with torch.no_grad():
            meshes, cond = posed_motion(run, sequence, params)
            g = (
                load_trained(run.dynamic_dir)
                .on_device("cpu", trained_precision(run.dynamic_dir))
                .pose(cond, meshes.vertices[t], t)
            )
    write_frame_ply(out, in_axes(g, np.eye(3), np.zeros(3)))
