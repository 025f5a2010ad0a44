"""interactavatar-export: every frame of a motion of a trained avatar as 3DGS PLY files, one per frame.

Not a stage: a reader of the artifacts of a finished run (the dynamic stage's model, the fit, the pbd stage's
offsets, the scene analysis); nothing is trained or re-run. A frame is posed exactly as the pipeline poses it:
a motion of the fit (the training motion as the method refined it, the held-out motion) as ``evaluate`` and the
viewer pose it, with the pbd stage's contact offsets when the method uses them; a params.parquet driver file as
``reenact`` drives the avatar with it (the motion transferred onto the subject, the contact simulated on its
face). The pose-dependent hand and the contact deformation are baked into each file.

Usage::

    interactavatar-export outputs/synth_a --motion test --out synth_a_test_ply
    interactavatar-export outputs/synth_a --motion driver/params.parquet --frames 0-9 --axes opengl --out clip
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from avatar.artifacts import (
    HELD_OUT_SEQUENCE,
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
from avatar.reenact import PLACEMENTS
from avatar.reenact.driving import drive, is_parameter_file, transferred_params
from avatar.render.gaussians import WorldGaussians
from avatar.representations import TrainedAvatar, load_trained
from avatar.templates.lbs import batch_rodrigues
from data_schemas.tables import SchemaError
from data_schemas.writes import write_json
from pipeline.device import DeviceUnavailable, resolve_device
from pipeline.manifest import MANIFEST_NAME
from pipeline.workspace import METHODS_DIR, method_run

PROG = "interactavatar-export"
#: --axes: the frame the files are written in (:func:`axes_frame`)
AXES = ("world", "opengl", "opencv")
#: what an export folder holds besides its PLY files
EXPORT_INFO = "export.json"
#: OpenGL's axes from OpenCV's and back: 180 degrees about x, (x, y, z) -> (x, -y, -z)
FLIP_YZ = np.diag([1.0, -1.0, -1.0])

AXES_HELP = """\
axes (--axes), all in metres:
  world   (default) the pipeline's world frame, as every artifact of the run: for the built-in
          synthetic capture y up, the subject facing +z, x to the subject's left; for a folder
          capture the frame of its calibration (its cameras.parquet, COLMAP model or nerfstudio
          transforms.json), whose up is the calibration's (a COLMAP model's world is often its
          first camera's frame: y down). The positions the pipeline renders.
  opengl  y up (three.js, Spark): rotated and moved so that the head of the training motion's
          first frame, as fitted, is upright at the origin: x the subject's left, y up, z the
          way the face looks; a camera on +z looking down -z sees the face. A point p of the
          world goes to R0^T (p - c0), R0 the head's rotation (flame_global_orient), c0 the
          centroid of its face mesh on that frame; every rotation is turned by R0^T.
  opencv  y down (OpenCV, COLMAP, the 3DGS training convention): opengl turned 180 degrees
          about x, (x, y, z) -> (x, -y, -z); the face looks towards -z.
Either way a file is one frame; scales, opacities and colours are unchanged; export.json in the
folder records the 4x4 matrix from world to file coordinates."""

LAYOUT_HELP = """\
each file: binary little-endian PLY, one vertex per Gaussian, float32 properties in the 3DGS
order x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2
rot_3: normals 0, colour as degree-0 spherical harmonics (rgb = 0.5 + 0.2820948 f_dc; no
f_rest_* properties: the avatar's colours have no higher bands), opacity a logit, scales the
natural log of the standard deviations, rot a unit quaternion w x y z."""


class ExportError(Exception):
    """What stops an export, one line that names the fix."""


@dataclass
class TrainedRun:
    """A subject's trained method run on disk: its folders and the settings its stages ran with (``model``,
    ``method.pbd``, ``stage.pbd.solver``, from their manifests) plus ``reenact.placement`` for driver files."""

    subject_dir: Path
    run: str
    cfg: DictConfig

    @property
    def dynamic_dir(self) -> Path:
        return self.subject_dir / METHODS_DIR / self.run / "dynamic"

    @property
    def fit_dir(self) -> Path:
        return self.subject_dir / "fit"

    def motions(self) -> list[str]:
        """The motions of the fit (its sequences: ``train``, ``test``, a synthetic capture's ``cross_<subject>``)."""
        return sorted(p.parent.name for p in self.fit_dir.glob("*/params.parquet"))


def _manifest(stage_dir: Path) -> dict | None:
    try:
        return json.loads((stage_dir / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return None


def _train_command(subject_dir: Path, method: str, seed: int) -> str:
    seed_arg = f" seed={seed}" if seed else ""
    return (
        f"interactavatar paths.outputs={subject_dir.parent} subject={subject_dir.name} method={method}{seed_arg} "
        "run.until=dynamic"
    )


def trained_run(
    subject_dir: Path,
    method: str = "interactavatar",
    seed: int = 0,
    *,
    placement: str = "contact",
    flame_path: str | None = None,
    mano_path: str | None = None,
) -> TrainedRun:
    """The trained run of ``method`` (seed ``seed``) under the subject folder ``subject_dir``; :class:`ExportError`
    naming the command that trains it when there is none. ``flame_path``/``mano_path`` replace the template files
    the run recorded (moved since)."""
    if not subject_dir.is_dir():
        raise ExportError(f"{subject_dir}: no such folder; give a subject's outputs folder (<paths.outputs>/<subject>)")
    run = method_run(method, seed)
    dynamic_dir = subject_dir / METHODS_DIR / run / "dynamic"
    dynamic, pbd = _manifest(dynamic_dir), _manifest(subject_dir / "pbd")
    if dynamic is None or pbd is None or not (subject_dir / "fit").is_dir():
        trained = sorted(p.parent.parent.name for p in subject_dir.glob(f"{METHODS_DIR}/*/dynamic/{MANIFEST_NAME}"))
        nested = sorted(p.parent.name for p in subject_dir.glob(f"*/{METHODS_DIR}"))
        if nested and not trained:
            raise ExportError(
                f"{subject_dir}: not a subject's outputs folder; give one, e.g. {subject_dir / nested[0]}"
            )
        there = f"; trained here: {', '.join(trained)} (--method, --seed)" if trained else ""
        raise ExportError(
            f"{subject_dir}: no trained model of method '{method}' seed {seed} ({dynamic_dir} has no "
            f"{MANIFEST_NAME}){there}; train it first: {_train_command(subject_dir, method, seed)} (with the "
            "dataset overrides the subject was captured with)"
        )
    if placement not in PLACEMENTS:
        raise ExportError(f"--placement {placement}: choose one of {', '.join(PLACEMENTS)}")
    cfg = OmegaConf.create({})
    for manifest in (pbd, dynamic):  # the model's files and the solver settings the run used
        for key, value in manifest["config"].items():
            OmegaConf.update(cfg, key, value, merge=True)
    if OmegaConf.select(cfg, "method.pbd") is None:
        raise ExportError(f"{dynamic_dir / MANIFEST_NAME}: records no method.pbd; rerun the dynamic stage")
    OmegaConf.update(cfg, "reenact.placement", placement)
    for key, given in (("flame_path", flame_path), ("mano_path", mano_path)):
        if given is not None:
            OmegaConf.update(cfg, f"model.{key}", given)
        path = OmegaConf.select(cfg, f"model.{key}")
        option = f"--{key.replace('_', '-')}"
        if given is not None and not Path(given).is_file():
            raise ExportError(f"{option} {given}: no such file")
        if path and not Path(str(path)).is_file():
            raise ExportError(
                f"model.{key}={path}: no such file; the run {run} was posed with it: pass {option} with where it is now"
            )
    return TrainedRun(subject_dir, run, cfg)


def motion_params(run: TrainedRun, motion: str) -> dict[str, np.ndarray]:
    """The parameters of ``motion``: a motion of the fit (:meth:`TrainedRun.motions`; the training motion as the
    method refined it) or a params.parquet file (the driver's own, before the transfer onto the subject)."""
    if is_parameter_file(motion):
        path = Path(motion)
        if not path.is_file():
            raise ExportError(f"--motion {motion}: no such file; {_motion_choices(run)}")
        try:
            return read_params(path)
        except SchemaError as exc:
            raise ExportError(f"--motion {motion}: not a params table ({exc}); {_motion_choices(run)}") from exc
    if motion not in run.motions():
        raise ExportError(f"--motion {motion}: unknown motion; {_motion_choices(run)}")
    return method_params(run.dynamic_dir, run.fit_dir, motion)


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
    order, each once; :class:`ExportError` for one outside 0..num_frames-1."""
    if spec.strip() == "all":
        return list(range(num_frames))
    frames: list[int] = []
    for part in spec.split(","):
        first, sep, last = part.strip().partition("-")
        try:
            lo, hi = int(first), int(last) if sep else int(first)
        except ValueError:
            raise ExportError(
                f"--frames {spec}: expected 'all' or frames and ranges such as 0,5,10-19 (the first frame is 0)"
            ) from None
        if lo > hi:
            raise ExportError(f"--frames {spec}: range {part.strip()} runs backwards")
        frames.extend(range(lo, hi + 1))
    outside = [t for t in frames if not 0 <= t < num_frames]
    if outside:
        raise ExportError(
            f"--frames {spec}: frame {outside[0]} out of range; motion '{motion}' has frames 0..{num_frames - 1}"
        )
    return list(dict.fromkeys(frames))


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
    temporary folder beside it that is renamed into place (replacing an earlier export only with ``overwrite``).
    The avatar poses the frames on the torch ``device``, its networks in the precision its training ran them in."""
    _check_destination(out, overwrite)
    params = motion_params(run, motion)
    num_frames = len(params["flame_global_orient"])
    chosen = parse_frames(frames, num_frames, motion)
    rotation, centre = axes_frame(run, axes)
    try:
        meshes, cond = posed_motion(run, motion, params)
        model = load_trained(run.dynamic_dir).on_device(device, trained_precision(run.dynamic_dir))
    except SchemaError as exc:
        raise ExportError(str(exc)) from exc
    partial = _partial_folder(out)
    try:
        names = _write_frames(partial, model, meshes.to(device), cond.to(device), chosen, rotation, centre, progress)
        world_to_file = np.eye(4)
        world_to_file[:3, :3], world_to_file[:3, 3] = rotation, -rotation @ centre
        write_json(
            partial / EXPORT_INFO,
            {
                "subject": run.subject_dir.name,
                "run": run.run,
                "motion": motion,
                "frames": chosen,
                "files": names,
                "gaussians": model.num_gaussians,
                "axes": axes,
                "world_to_file": world_to_file.tolist(),
                "units": "metres",
            },
            "the export's description",
        )
        _publish(partial, out)
    except OSError as exc:
        raise ExportError(str(exc)) from exc
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return [out / name for name in names]


def _partial_folder(out: Path) -> Path:
    """A new empty folder beside ``out`` (same disk: renamed into place when done), never read as an export."""
    blocker = next((p for p in (out.parent, *out.parent.parents) if os.path.lexists(p)), None)
    if blocker is not None and not blocker.is_dir():
        raise ExportError(f"--out {out}: {blocker} is not a folder; choose another place")
    partial = out.parent / f".{out.name}.{uuid.uuid4().hex[:12]}.partial"
    try:
        partial.mkdir(parents=True)
    except OSError as exc:
        raise ExportError(f"--out {out}: cannot write there ({exc.strerror or exc}); choose another folder") from exc
    return partial


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


def _check_destination(out: Path, overwrite: bool) -> None:
    """Refuse an ``out`` that exists, unless ``overwrite`` and it is an earlier export (PLY files and export.json)."""
    if not os.path.lexists(out):
        return
    if not out.is_dir() or out.is_symlink():
        raise ExportError(f"--out {out}: exists and is not a folder; choose another")
    if not overwrite:
        raise ExportError(f"--out {out}: exists; pass --overwrite to replace an earlier export, or choose another")
    others = [p.name for p in out.iterdir() if not (p.suffix == ".ply" or p.name == EXPORT_INFO) or p.is_dir()]
    if others:
        raise ExportError(
            f"--out {out}: holds files an export does not write ({', '.join(sorted(others)[:3])}); "
            "--overwrite replaces only an earlier export's folder: choose another"
        )


def _publish(partial: Path, out: Path) -> None:
    """Rename the finished ``partial`` folder to ``out``; an earlier export there is moved aside first and removed
    after, so ``out`` holds the old export or the new one at every instant."""
    if not os.path.lexists(out):
        partial.rename(out)
        return
    aside = out.parent / f".{out.name}.{uuid.uuid4().hex[:12]}.old"
    aside.mkdir()
    out.rename(aside / out.name)
    try:
        partial.rename(out)
    except OSError:
        (aside / out.name).rename(out)
        raise
    finally:
        shutil.rmtree(aside, ignore_errors=True)


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
    run = trained_run(subject_dir, method, seed)
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


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Write every frame (or the frames you name) of a motion of a trained avatar as 3DGS PLY\n"
            "files, one per frame, with the pose-dependent hand and the contact deformation baked in\n"
            "as the pipeline poses them. Reads the trained model; nothing is retrained."
        ),
        epilog=f"{AXES_HELP}\n\n{LAYOUT_HELP}\n\nexamples:\n"
        f"  {PROG} outputs/synth_a --motion test --out synth_a_test\n"
        f"  {PROG} outputs/synth_a --motion train --frames 0-9 --axes opengl --out train_0-9\n"
        f"  {PROG} outputs/synth_a --motion outputs/synth_b/fit/test/params.parquet --out driven",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subject", type=Path, help="a subject's outputs folder (<paths.outputs>/<subject>)")
    p.add_argument(
        "--motion",
        default=HELD_OUT_SEQUENCE,
        help="a motion of the fit: train (the training motion, as the method refined it), test (the held-out "
        "motion; the default), a synthetic capture's cross_<subject>; or a params.parquet file (the fit's schema: "
        "another subject's fit/<motion>/params.parquet, a reenactment's), which drives the avatar as the reenact "
        "stage does",
    )
    p.add_argument("--out", type=Path, required=True, help="the folder to write (created; refused if it exists)")
    p.add_argument("--method", default="interactavatar", help="the trained method (default: interactavatar)")
    p.add_argument("--seed", type=int, default=0, help="the training run's seed (default: 0)")
    p.add_argument("--frames", default="all", help="all (default), or frames and ranges such as 0,5,10-19")
    p.add_argument("--axes", default="world", choices=AXES, help="the frame the files are in (below)")
    p.add_argument(
        "--placement",
        default="contact",
        choices=PLACEMENTS,
        help="a driver file's hand on the subject, as reenact.placement (default: contact)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace the folder of an earlier export")
    p.add_argument("--flame-path", default=None, help="the official FLAME file, if the run used one and it moved")
    p.add_argument("--mano-path", default=None, help="the official MANO file, if the run used one and it moved")
    p.add_argument("--quiet", action="store_true", help="no line per frame")
    p.add_argument(
        "--device",
        default="auto",
        help="where the avatar poses the frames: auto (default: a CUDA GPU where there is one), cpu, cuda, cuda:N",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    progress = None if args.quiet else lambda line: print(line, file=sys.stderr, flush=True)
    try:
        device = resolve_device(args.device)
    except DeviceUnavailable as exc:
        print(f"{PROG}: {str(exc).replace('run.device=', '--device ')}", file=sys.stderr)
        return 2
    try:
        run = trained_run(
            args.subject,
            args.method,
            args.seed,
            placement=args.placement,
            flame_path=args.flame_path,
            mano_path=args.mano_path,
        )
        written = export_motion(
            run,
            args.motion,
            args.out,
            frames=args.frames,
            axes=args.axes,
            overwrite=args.overwrite,
            progress=progress,
            device=device,
        )
    except (ExportError, SchemaError, OSError) as exc:
        print(f"{PROG}: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing written to {args.out}", file=sys.stderr)
        return 130
    print(f"{len(written)} PLY files ({args.axes} axes) in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
