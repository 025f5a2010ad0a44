"""Stage ``pbd``: per-frame face offsets where the hand presses the face (XPBD), or taken from elsewhere.

``stage.pbd.source``: ``simulate`` (the XPBD solver of :mod:`avatar.pbd`), ``ground_truth`` (the
synthetic capture's own deformation), ``provided`` (the dataset's, e.g. DECAF's ``deforms.npy``
as the capture adapter imported it) or ``none`` (zero offsets: the "w/o PBD" ablation). When the scene
stage decides against PBD (no hand, or no contact in any training frame), every source gives zero offsets
and no contact, nothing is simulated, and the report says why.

Writes per sequence ``deform.parquet`` (world-frame offsets *added* to the posed face; see
:mod:`avatar.pbd.convention`) and ``contacts.parquet`` (per-vertex contact flags), and
``pbd_report.json``: per frame whether it was simulated, iterations, residual penetration, largest
offset; the errors against the ground truth where the capture has it. Wall times go to the
manifest's metrics only, so rerunning the stage on the same inputs writes identical bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatar.artifacts import load_scene
from avatar.artifacts.dependencies import contact_sources, stiffness_file_problems, unused_solver_settings
from avatar.artifacts.motion import templates
from avatar.pbd import (
    PBDConfig,
    SequenceDeformation,
    detect_contacts,
    moving_vertex_errors,
    simulate_sequence,
    single_threaded,
)
from avatar.posing import posed_keypoints
from avatar.reenact.driving import face_stiffness, pbd_solver_config
from avatar.templates import TemplateModel
from data_schemas.capture import CaptureIndex, SequenceInfo, gt_path, provided_path
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import SchemaError, read_table, write_table
from data_schemas.writes import write_json
from pipeline.stage import StageContext, stage

SOURCES = ("simulate", "ground_truth", "provided", "none")


@dataclass
class PBDStageConfig:
    """Types of ``stage.pbd`` (values in conf/stage/pbd.yaml): where the offsets come from, and the
    solver's settings (:class:`avatar.pbd.PBDConfig`)."""

    source: str
    solver: PBDConfig


@stage(
    "pbd",
    inputs=("capture", "fit", "scene"),
    config_keys=("model", "stage.pbd"),
    outputs=("train/deform.parquet", "train/contacts.parquet", "pbd_report.json"),
    version="2",
    config_schema=PBDStageConfig,
    sources=contact_sources,
    unused_keys=unused_solver_settings,
    checks=stiffness_file_problems,
)
def pbd(ctx: StageContext) -> None:
    """Face offsets and contact flags per frame from stage.pbd.source; pbd_report.json."""
    conf = ctx.cfg.stage.pbd
    if conf.source not in SOURCES:
        raise SchemaError(f"stage.pbd.source={conf.source!r}: choose one of {SOURCES}")
    solver = pbd_solver_config(ctx.cfg)
    cap_dir, fit_dir = ctx.input_dir("capture"), ctx.input_dir("fit")
    index = CaptureIndex.read(cap_dir)
    head, hand = templates(ctx.cfg.model)
    stiffness = None
    report: dict = {
        "source": conf.source,
        "frame_convention": "world-frame offsets added to the posed face",
        "sequences": {},
    }
    scene = load_scene(ctx.input_dir("scene"))
    if not scene.model_pbd:
        report["skipped"] = f"scene analysis: {scene.why['model_pbd']}"
    elif conf.source == "simulate":
        stiffness, report["stiffness"] = face_stiffness(ctx.cfg, head, solver)
    faces, hand_faces = torch.from_numpy(np.array(head.faces)), torch.from_numpy(np.array(hand.faces))
    preds, refs, contacts, seconds = [], [], [], []
    for seq, info in ctx.progress(list(index.sequences.items()), desc="pbd: sequences"):
        table = read_table(fit_dir / seq / "params.parquet", PARAMS)
        posed = posed_keypoints({k: np.asarray(table[k]) for k in PARAM_COLUMNS}, head, hand)
        face, hand_v = torch.from_numpy(posed["face_vertices"]), torch.from_numpy(posed["hand_vertices"])
        if not scene.model_pbd:
            deform = _skipped(face.shape[0], face.shape[1], hand_v.shape[1])
        elif stiffness is not None:
            deform = simulate_sequence(face, hand_v, faces, hand_faces, stiffness, solver)
        else:
            deform = _from_source(conf.source, cap_dir, seq, info, face, hand_v, faces, hand_faces, head, solver)
        _write(ctx.out_dir / seq, deform)
        entry: dict = {"frames": deform.frames}
        if info.has_ground_truth:
            gt = read_table(gt_path(cap_dir, seq, "deform"), DEFORM)
            ref = np.asarray(gt["offsets"], np.float64).reshape(deform.offsets.shape)
            errors = moving_vertex_errors(deform.offsets, ref, np.asarray(gt["contact"], bool))
            entry["ground_truth_error"] = errors.as_dict() if errors else None
            preds.append(deform.offsets)
            refs.append(ref)
            contacts.append(np.asarray(gt["contact"], bool))
        report["sequences"][seq] = entry
        seconds += deform.seconds
    write_json(ctx.out_dir / "pbd_report.json", report, "PBD report")
    _metrics(ctx, report, preds, refs, contacts, seconds)


def _from_source(
    source: str,
    cap_dir: Path,
    seq: str,
    info: SequenceInfo,
    face: torch.Tensor,
    hand: torch.Tensor,
    faces: torch.Tensor,
    hand_faces: torch.Tensor,
    head: TemplateModel,
    cfg: PBDConfig,
) -> SequenceDeformation:
    """Offsets from the ground truth, the dataset, or zeros; contact flags detected on the undeformed
    meshes (or the dataset's own contacts for ``provided``, when it ships them)."""
    T, V = face.shape[:2]
    if source == "none":
        offsets = np.zeros((T, V, 3))
    else:
        if source == "ground_truth" and not info.has_ground_truth:
            raise SchemaError(
                f"{cap_dir / seq}: stage.pbd.source=ground_truth needs a capture with ground truth "
                f"(dataset=synthetic); use simulate, provided or none"
            )
        if source == "provided" and not info.has_provided("deform"):
            raise SchemaError(
                f"{cap_dir / seq}: stage.pbd.source=provided needs deformations shipped with the "
                f"dataset (provided/deform.parquet, dataset=decaf with the official FLAME); use simulate"
            )
        path = gt_path(cap_dir, seq, "deform") if source == "ground_truth" else provided_path(cap_dir, seq, "deform")
        offsets = np.asarray(read_table(path, DEFORM)["offsets"], np.float64)
        if offsets.shape != (T, V * 3):
            raise SchemaError(
                f"{path}: offsets of shape {offsets.shape}, but the fit has {T} frames of a "
                f"{head.num_vertices}-vertex head (expected ({T}, {V * 3}))"
            )
        offsets = offsets.reshape(T, V, 3)
    with single_threaded():
        flags = [detect_contacts(face[t], hand[t], hand_faces, faces, cfg) for t in range(T)]
    face_contact = np.stack([f.numpy() for f, _ in flags])
    hand_contact = np.stack([h.numpy() for _, h in flags])
    if source == "provided" and info.has_provided("contacts"):
        shipped = read_table(provided_path(cap_dir, seq, "contacts"), CONTACTS)
        face_contact, hand_contact = np.asarray(shipped["face"]) > 0.5, np.asarray(shipped["hand"]) > 0.5
    out = SequenceDeformation(offsets, face_contact, hand_contact)
    out.frames = [
        {
            "frame": t,
            "near": bool(face_contact[t].any()),
            "simulated": False,
            "iterations": 0,
            "contact_vertices": int(face_contact[t].sum()),
            "max_offset_mm": float(np.linalg.norm(offsets[t], axis=1).max()) * 1e3,
        }
        for t in range(T)
    ]
    return out


def _skipped(T: int, V: int, Vh: int) -> SequenceDeformation:
    """Zero offsets and no contact for T frames (V face, Vh hand vertices): PBD not modelled."""
    out = SequenceDeformation(np.zeros((T, V, 3)), np.zeros((T, V), bool), np.zeros((T, Vh), bool))
    out.frames = [
        {"frame": t, "near": False, "simulated": False, "iterations": 0, "contact_vertices": 0, "max_offset_mm": 0.0}
        for t in range(T)
    ]
    return out


def _write(seq_dir: Path, deform: SequenceDeformation) -> None:
    """deform.parquet and contacts.parquet of one sequence."""
    T = deform.offsets.shape[0]
    contact = deform.face_contact.any(axis=1) | (np.abs(deform.offsets).reshape(T, -1).max(axis=1) > 0)
    write_table(
        seq_dir / "deform.parquet",
        DEFORM,
        {"frame": np.arange(T), "contact": contact, "offsets": deform.offsets.reshape(T, -1)},
    )
    write_table(
        seq_dir / "contacts.parquet",
        CONTACTS,
        {
            "frame": np.arange(T),
            "contact": deform.face_contact.any(axis=1),
            "face": deform.face_contact.astype(np.float32),
            "hand": deform.hand_contact.astype(np.float32),
        },
    )


def _metrics(
    ctx: StageContext,
    report: dict,
    preds: list[np.ndarray],
    refs: list[np.ndarray],
    contacts: list[np.ndarray],
    seconds: list[float],
) -> None:
    """simulated_frames, penetration_max_mm, the ground-truth errors pooled over sequences, and the
    mean wall time per simulated (contact) frame."""
    rows = [f for s in report["sequences"].values() for f in s["frames"]]
    simulated = [f for f in rows if f["simulated"]]
    ctx.metrics["simulated_frames"] = len(simulated)
    ctx.metrics["contact_frames"] = sum(f["contact_vertices"] > 0 for f in rows)
    ctx.metrics["penetration_max_mm"] = max((f["penetration_max_mm"] for f in simulated), default=0.0)
    if preds:
        errors = moving_vertex_errors(np.concatenate(preds), np.concatenate(refs), np.concatenate(contacts))
        if errors is not None:
            ctx.metrics["gt_vertex_error_mm"] = errors.mean_mm
            ctx.metrics["zero_offset_error_mm"] = errors.zero_mean_mm
    if seconds:
        ctx.metrics["pbd_s_per_contact_frame"] = float(np.mean(seconds))
