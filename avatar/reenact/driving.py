"""Driving an avatar with a motion that was not trained on (reenactment): the driver named by ``reenact.driver``,
the motion transferred onto the target's identity, and the contact simulated on the face as the pbd stage does."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from avatar.artifacts import load_params, read_params
from avatar.artifacts.motion import templates
from avatar.dynamic import sequence_conditioning
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.pbd import PBDConfig, StiffnessFileError, face_relative_stiffness, simulate_sequence
from avatar.posing import MeshSequence, posed_keypoints, posed_meshes
from avatar.reenact import PLACEMENTS, MotionTransfer, MotionTransferError, parameter_problem, transfer_motion
from avatar.scene import SceneDecision
from avatar.templates import TemplateModel
from data_schemas.tables import SchemaError


def driver_subject(cfg: DictConfig) -> str | None:
    """The other subject ``reenact.driver`` names, or ``None`` (``self`` or a parameter file)."""
    driver = str(cfg.reenact.driver)
    return None if driver == "self" or is_parameter_file(driver) else driver


def is_parameter_file(driver: str) -> bool:
    """Whether ``reenact.driver`` names a file rather than ``self`` or a subject (whose names hold neither a '/'
    nor a '.': :data:`pipeline.workspace.SUBJECT_RULE`)."""
    return "/" in driver or "." in driver


#: what ``reenact.driver`` may name, for its messages
DRIVER_CHOICES = "give a params.parquet (the fit stage's schema), 'self', or a subject of this outputs folder"


def driver_file_problem(driver: str) -> str | None:
    """Why the file ``reenact.driver`` names cannot drive an avatar (missing, not ``.parquet``, not a table of the
    fit stage's params schema, values no capture holds: :func:`avatar.reenact.parameter_problem`), or ``None``;
    reads the table, which is small (a row per frame)."""
    path = Path(driver)
    if not path.is_file():
        return f"reenact.driver={driver}: no such file; {DRIVER_CHOICES}"
    if path.suffix != ".parquet":
        return f"reenact.driver={driver}: not a .parquet file; {DRIVER_CHOICES}"
    try:
        params = read_params(path)
    except SchemaError as exc:
        return f"reenact.driver={driver}: not a params table ({exc}); {DRIVER_CHOICES}"
    problem = parameter_problem(params)
    return None if problem is None else f"reenact.driver={driver}: {problem}"


def placement_problem(cfg: DictConfig) -> str | None:
    """Why ``reenact.placement`` is not a placement of :func:`avatar.reenact.transfer_motion`, or ``None``."""
    placement = str(cfg.reenact.placement)
    return None if placement in PLACEMENTS else f"reenact.placement={placement}: choose one of {', '.join(PLACEMENTS)}"


@dataclass
class DrivenSequence:
    """A parameter sequence on the target's avatar: the meshes (face deformed by the simulated contact), the
    model's conditioning, the offsets (T, V, 3), the pbd rows per frame (empty without PBD), the head-size
    ratio target / driver and where the face stiffness came from (None without PBD)."""

    params: dict[str, np.ndarray]
    meshes: MeshSequence
    cond: SequenceConditioning
    offsets: np.ndarray
    pbd_frames: list[dict]
    head_scale: float
    stiffness_source: str | None


def drive(
    cfg: DictConfig, params: dict[str, np.ndarray], scene: SceneDecision, head_scale: float = 1.0
) -> DrivenSequence:
    """Pose ``params`` (already on the target's identity) and, for methods with ``method.pbd`` on a scene
    whose analysis models PBD, simulate the contact on the face with the pbd stage's solver, settings and
    stiffness, as the pbd stage does."""
    head, hand = templates(cfg.model)
    posed = posed_keypoints(params, head, hand)
    face_v, hand_v = torch.from_numpy(posed["face_vertices"]), torch.from_numpy(posed["hand_vertices"])
    if bool(cfg.method.pbd) and scene.model_pbd:
        solver = pbd_solver_config(cfg)
        stiffness, stiffness_source = face_stiffness(cfg, head, solver)
        deform = simulate_sequence(
            face_v, hand_v, torch.tensor(np.array(head.faces)), torch.tensor(np.array(hand.faces)), stiffness, solver
        )
        offsets, frames = deform.offsets, deform.frames
    else:
        offsets, frames, stiffness_source = np.zeros(face_v.shape), [], None
    meshes = posed_meshes(params, head, hand)
    meshes.vertices[:, : head.num_vertices] += torch.from_numpy(offsets).to(meshes.vertices.dtype)
    cond = sequence_conditioning(params, head, hand, torch.from_numpy(offsets))
    return DrivenSequence(params, meshes, cond, offsets, frames, head_scale, stiffness_source)


def transferred_params(
    cfg: DictConfig, target_fit_dir: Path, driver: dict[str, np.ndarray], source: Path
) -> MotionTransfer:
    """The driver's motion on the target whose fit is ``target_fit_dir`` (its train sequence's identity), placed
    as ``reenact.placement`` says; one error naming ``source`` when the driver cannot drive it."""
    problem = placement_problem(cfg)
    if problem is not None:
        raise SchemaError(problem)
    head, hand = templates(cfg.model)
    try:
        return transfer_motion(load_params(target_fit_dir, "train"), driver, head, hand, str(cfg.reenact.placement))
    except MotionTransferError as exc:
        raise SchemaError(f"{source}: cannot drive the avatar: {exc}") from exc


def transfer_summary(frames: list[dict]) -> dict[str, float]:
    """Manifest metrics of a contact-preserving transfer's per-frame report (empty for the scaled placement):
    frames whose driver's hand touches its face, the fraction of the touching points that touch the target's face
    too, and their mean residual distance from the same surface points (mm, over the touching frames)."""
    if not frames:
        return {}
    touching = [f for f in frames if f["touching_points"]]
    return {
        "transfer_touch_frames": len(touching),
        "transfer_kept_fraction": (
            sum(f["kept_points"] for f in touching) / max(1, sum(f["touching_points"] for f in touching))
        ),
        "transfer_residual_mm": float(np.mean([f["residual_mm"] for f in touching])) if touching else 0.0,
    }


def pbd_solver_config(cfg: DictConfig) -> PBDConfig:
    """The XPBD solver's settings of ``stage.pbd.solver`` (one clear error when out of range)."""
    try:
        settings = OmegaConf.to_container(cfg.stage.pbd.solver, resolve=True)
        if not isinstance(settings, dict):
            raise ValueError(f"must be a mapping of the solver's settings, got {settings!r}")
        return PBDConfig(**{str(key): value for key, value in settings.items()})  # a section's keys are names
    except ValueError as exc:
        raise SchemaError(f"stage.pbd.solver: {exc}") from exc


def face_stiffness(cfg: DictConfig, head: TemplateModel, solver: PBDConfig) -> tuple[torch.Tensor, str]:
    """(V,) relative attachment stiffness of the face and where it came from (``model.face_stiffness_path``,
    the template's skin-to-skull distance, or a uniform estimate)."""
    try:
        rel, source = face_relative_stiffness(
            head.num_vertices,
            head.inner_distance,
            cfg.model.get("face_stiffness_path"),
            solver.reference_thickness_m,
            solver.stiffness_power,
        )
    except StiffnessFileError as exc:
        raise SchemaError(f"model.face_stiffness_path: {exc}") from exc
    return torch.from_numpy(rel), source
