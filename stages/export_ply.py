"""Export any frame of a trained dynamic avatar as a world-space 3DGS PLY (not a stage: a reader of artifacts).

Usage::

    python -m stages.export_ply --outputs outputs --subject synth_a --method interactavatar --sequence test \
        --frame 3 --out frame3.ply

The frame is posed with the fit stage's parameters of ``--sequence`` (of the train motion: as the method refined
them while training, its ``dynamic/params.parquet``) and, when the method uses them, the pbd
stage's offsets, exactly as ``evaluate`` renders it; splat viewers open the file directly.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from omegaconf import OmegaConf

from pipeline.manifest import MANIFEST_NAME
from pipeline.workspace import METHODS_DIR
from stages.artifacts import method_params, write_frame_ply
from stages.posing import load_sequence
from stages.representations import load_trained


def export_frame(
    subject_dir: Path,
    sequence: str,
    frame: int,
    out: Path,
    method: str = "interactavatar",
    flame_path: str | None = None,
    mano_path: str | None = None,
) -> None:
    """Write frame ``frame`` of ``sequence`` of ``method``'s trained model under ``subject_dir`` to ``out``."""
    dynamic_dir = subject_dir / METHODS_DIR / method / "dynamic"
    if not (dynamic_dir / MANIFEST_NAME).is_file():
        raise SystemExit(
            f"{dynamic_dir}: no trained model of method '{method}'; train it first "
            f"(interactavatar subject={subject_dir.name} method={method})"
        )
    uses_pbd = bool(json.loads((dynamic_dir / MANIFEST_NAME).read_text())["config"]["method.pbd"])
    cfg = OmegaConf.create({"model": {"flame_path": flame_path, "mano_path": mano_path}})
    fit_dir = subject_dir / "fit"
    meshes, cond = load_sequence(
        fit_dir,
        sequence,
        cfg,
        pbd_dir=subject_dir / "pbd" if uses_pbd else None,
        params=method_params(dynamic_dir, fit_dir, sequence),
    )
    num_frames = meshes.vertices.shape[0]
    if not 0 <= frame < num_frames:
        raise SystemExit(
            f"{fit_dir / sequence / 'params.parquet'}: frame {frame} out of range; "
            f"sequence '{sequence}' has frames 0..{num_frames - 1}"
        )
    model = load_trained(dynamic_dir)
    with torch.no_grad():
        write_frame_ply(out, model.pose(cond, meshes.vertices[frame], frame))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, default=Path("outputs"))
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--method", default="interactavatar")
    parser.add_argument("--sequence", default="train")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--flame-path", default=None, help="the model.flame_path the run used, if any")
    parser.add_argument("--mano-path", default=None, help="the model.mano_path the run used, if any")
    args = parser.parse_args()
    export_frame(
        args.outputs / args.subject, args.sequence, args.frame, args.out, args.method, args.flame_path, args.mano_path
    )
    print(args.out)


if __name__ == "__main__":
    main()
