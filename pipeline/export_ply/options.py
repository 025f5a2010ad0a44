"""The command line of ``interactavatar-export`` and what stops an export: the standard library only, so that the
command reads its arguments, and prints its help, before torch and the core load."""

from __future__ import annotations

import argparse
from pathlib import Path

PROG = "interactavatar-export"
#: how long an export waits for a run that is rewriting an artifact the export reads (seconds) before it gives up
LOCK_WAIT_S = 10.0
#: --axes: the frame the files are written in (:func:`pipeline.export_ply.frames.axes_frame`)
AXES = ("world", "opengl", "opencv")

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

SAFETY_HELP = """\
what it reads and writes: it reads the run's artifacts under their locks, so no run rewrites
them meanwhile, and only when each still is what the pipeline would keep (none computed from
an artifact republished since); --out must lie outside every subject's outputs, and
--overwrite replaces only a folder an earlier export wrote (its export.json lists its files).
A failed, interrupted (Ctrl-C) or terminated (SIGTERM) export leaves nothing behind."""


class ExportError(Exception):
    """What stops an export, one line that names the fix."""


def parser() -> argparse.ArgumentParser:
    """The command line: a subject's outputs folder, --out and the options that choose what is written."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Write every frame (or the frames you name) of a motion of a trained avatar as 3DGS PLY\n"
            "files, one per frame, with the pose-dependent hand and the contact deformation baked in\n"
            "as the pipeline poses them. Reads the trained model; nothing is retrained."
        ),
        epilog=f"{AXES_HELP}\n\n{LAYOUT_HELP}\n\n{SAFETY_HELP}\n\nexamples:\n"
        f"  {PROG} outputs/synth_a --motion test --out synth_a_test\n"
        f"  {PROG} outputs/synth_a --motion train --frames 0-9 --axes opengl --out train_0-9\n"
        f"  {PROG} outputs/synth_a --motion outputs/synth_b/fit/test/params.parquet --out driven",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subject", type=Path, help="a subject's outputs folder (<paths.outputs>/<subject>)")
    p.add_argument(
        "--motion",
        default=None,
        help="a motion of the fit: train (the training motion, as the method refined it), test (the held-out "
        "motion; the default), a synthetic capture's cross_<subject>; or a params.parquet file (the fit's schema: "
        "another subject's fit/<motion>/params.parquet, a reenactment's), which drives the avatar as the reenact "
        "stage does",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="the folder to write, outside every subject's outputs (created; refused if it exists)",
    )
    p.add_argument("--method", default="interactavatar", help="the trained method (default: interactavatar)")
    p.add_argument("--seed", type=int, default=0, help="the training run's seed (default: 0)")
    p.add_argument("--frames", default="all", help="all (default), or frames and ranges such as 0,5,10-19")
    p.add_argument("--axes", default="world", choices=AXES, help="the frame the files are in (below)")
    p.add_argument(
        "--placement",
        default="contact",
        help="a driver file's hand on the subject, as reenact.placement (default: contact)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace the folder of an earlier export (and nothing else)"
    )
    p.add_argument("--flame-path", default=None, help="the official FLAME file, if the run used one and it moved")
    p.add_argument("--mano-path", default=None, help="the official MANO file, if the run used one and it moved")
    p.add_argument("--quiet", action="store_true", help="no line per frame")
    p.add_argument(
        "--device",
        default="auto",
        help="where the avatar poses the frames: auto (default: a CUDA GPU where there is one), cpu, cuda, cuda:N",
    )
    return p
