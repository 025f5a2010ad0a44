"""Artifact loaders shared by several stages (not a stage itself: stages still talk only through artifacts)."""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from avatar.dynamic import DynamicAvatar, DynamicModelConfig, sequence_conditioning
from avatar.dynamic.conditioning import Conditioning, SequenceConditioning
from avatar.gaussians.model import BoundGaussians
from avatar.pbd import PBDConfig, StiffnessFileError, face_relative_stiffness, simulate_sequence
from avatar.pbd.problem import unused_settings as unused_pbd_settings
from avatar.posing import MeshSequence, posed_keypoints, posed_meshes
from avatar.reenact import PLACEMENTS, MotionTransfer, MotionTransferError, transfer_motion
from avatar.scene import SceneDecision
from avatar.splatting import EmbeddedGaussians
from avatar.templates import TemplateModel, load_official_model, procedural_hand, procedural_head
from avatar.training.data import ViewSet
from avatar.training.frame_params import FrameParams, ParamLearningRates, parameter_movement
from avatar.training.splatting import SplattingConfig
from avatar.training.validation import FlatStop, ValidationConfig, Validator
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, SequenceInfo, gt_path, provided_path
from data_schemas.curve import CURVE
from data_schemas.gaussians import BOUND_GAUSSIANS
from data_schemas.gaussians_ply import GaussianCloud, write_gaussians_ply
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.frames import FRAMES_INDEX, crop_mask_path, rgb_path
from data_schemas.images import read_png
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.splatting import EMBEDDED_GAUSSIANS
from data_schemas.tables import SchemaError, read_table, write_table
from pipeline.sources import SourceFiles
from pipeline.stage import StageContext


class WorldGaussians(Protocol):
    """Gaussians of one frame in world space: means (N, 3), scales (N, 3), quats (N, 4), opacities (N,),
    colors (N, 3)."""

    means: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor




def templates(model_cfg: DictConfig) -> tuple[TemplateModel, TemplateModel]:
    """(head, hand): the official FLAME/MANO files when configured, else the procedural templates."""
    head = load_official_model(model_cfg.flame_path, "flame") if model_cfg.flame_path else procedural_head()
    hand = load_official_model(model_cfg.mano_path, "mano") if model_cfg.mano_path else procedural_hand()
    return head, hand


def load_ground_truth_params(capture_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The capture's ground-truth FLAME/MANO parameters of ``sequence``."""
    index = CaptureIndex.read(capture_dir)
    if not index.sequences[sequence].has_ground_truth:
        raise SchemaError(f"{capture_dir}: fit.source=ground_truth needs a capture with ground truth "
                          f"(dataset=synthetic); this one has none")
    table = read_table(gt_path(capture_dir, sequence, "params"), PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


def load_provided_params(capture_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The FLAME/MANO parameters the dataset ships for ``sequence`` (DECAF's multi-view fit)."""
    index = CaptureIndex.read(capture_dir)
    info = index.sequences[sequence]
    if not info.has_provided("params"):
        why = "".join(f"; {note}" for note in info.notes if "param" in note)
        raise SchemaError(f"{capture_dir / sequence}: fit.source=provided needs parameters shipped with the dataset "
                          f"(dataset=decaf), but the '{index.dataset}' capture of '{index.subject}' has none for "
                          f"sequence '{sequence}'{why}")
    table = read_table(provided_path(capture_dir, sequence, "params"), PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


GROUND_TRUTH_CONTACTS = "ground truth"
SHIPPED_CONTACTS = "shipped with the dataset"


def contact_source(info: SequenceInfo) -> str | None:
    """Where a sequence's contact labels come from: :data:`GROUND_TRUTH_CONTACTS` (the generator's),
    :data:`SHIPPED_CONTACTS` (e.g. DECAF's) or None (no labels)."""
    if info.has_ground_truth:
        return GROUND_TRUTH_CONTACTS
    return SHIPPED_CONTACTS if info.has_provided("contacts") else None


def contact_frames(capture_dir: Path, sequence: str, num_frames: int) -> np.ndarray:
    """(T,) bool: frames where the hand touches the face, from ground truth or the contacts the dataset
    ships (:func:`contact_source`); all False when unknown."""
    source = contact_source(CaptureIndex.read(capture_dir).sequences[sequence])
    if source == GROUND_TRUTH_CONTACTS:
        return np.asarray(read_table(gt_path(capture_dir, sequence, "deform"), DEFORM)["contact"], dtype=bool)
    if source == SHIPPED_CONTACTS:
        return np.asarray(read_table(provided_path(capture_dir, sequence, "contacts"), CONTACTS)["contact"], dtype=bool)
    return np.zeros(num_frames, dtype=bool)


def load_params(fit_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The fit stage's per-frame FLAME/MANO parameters of ``sequence`` (the columns of ``params.parquet``)."""
    return read_params(fit_dir / sequence / "params.parquet")


def contact_flags(pbd_dir: Path, sequence: str, num_frames: int) -> np.ndarray:
    """(T,) bool: frames in which the pbd stage found the hand touching the face (``deform.parquet``)."""
    path = pbd_dir / sequence / "deform.parquet"
    contact = np.asarray(read_table(path, DEFORM)["contact"], dtype=bool)
    if contact.shape != (num_frames,):
        raise SchemaError(f"{path}: {contact.shape[0]} frames, expected {num_frames}; rerun the pbd stage")
    return contact


def applied_deformation(cfg: DictConfig, pbd_dir: Path) -> Path | None:
    """``pbd_dir`` when the method deforms the face with the pbd stage's offsets (``method.pbd``), else
    ``None``: the "w/o PBD" ablation and the baselines pose undeformed meshes and give I ``d_j = 0``."""
    return pbd_dir if bool(cfg.method.pbd) else None


def load_sequence(fit_dir: Path, sequence: str, cfg: DictConfig, *, pbd_dir: Path | None,
                  params: dict[str, np.ndarray] | None = None) -> tuple[MeshSequence, Conditioning]:
    """Posed face + hand meshes of every frame of ``sequence`` from the fit stage's ``params.parquet`` (or from
    ``params``, e.g. a method's refined ones: :func:`method_params`), the face deformed by the pbd stage's contact
    offsets (``pbd_dir``; None: undeformed), and the dynamic model's conditioning of every frame."""
    posed = posed_sequence(fit_dir, sequence, cfg, pbd_dir, params)
    return posed.meshes, posed.conditioning(cfg)


@dataclass
class PosedSequence:
    """A sequence's parameters (the params.parquet columns), its posed meshes (the face's contact offsets added)
    and those offsets (T, V_face, 3) in metres (zeros without pbd)."""

    params: dict[str, np.ndarray]
    meshes: MeshSequence
    offsets: np.ndarray

    def conditioning(self, cfg: DictConfig) -> Conditioning:
        """The dynamic model's conditioning of every frame."""
        head, hand = templates(cfg.model)
        return sequence_conditioning(self.params, head, hand, torch.from_numpy(self.offsets))


def posed_sequence(fit_dir: Path, sequence: str, cfg: DictConfig, pbd_dir: Path | None,
                   params: dict[str, np.ndarray] | None = None) -> PosedSequence:
    """``sequence`` posed with ``params`` (default: the fit stage's) and the pbd stage's offsets (``pbd_dir``)."""
    head, hand = templates(cfg.model)
    params = load_params(fit_dir, sequence) if params is None else params
    meshes = posed_meshes(params, head, hand)
    num_frames = meshes.vertices.shape[0]
    if pbd_dir is None:
        return PosedSequence(params, meshes, np.zeros((num_frames, head.num_vertices, 3)))
    offsets = load_face_offsets(pbd_dir, sequence, num_frames, head.num_vertices)
    # posed_meshes concatenates the parts in order, face first: its vertices are the first V
    meshes.vertices[:, :head.num_vertices] += torch.from_numpy(offsets).to(meshes.vertices.dtype)
    return PosedSequence(params, meshes, offsets)


TRAIN_SEQUENCE = "train"
REFINE_PARAMS = ("auto", "true", "false")


def method_params(trained_dir: Path, fit_dir: Path, sequence: str) -> dict[str, np.ndarray]:
    """The parameters a trained method poses ``sequence`` with: for the train motion, those its training refined
    (``params.parquet`` of its warmup or dynamic stage ``trained_dir``; the fit's where it refined nothing); for
    any other sequence the fit's (the held-out motion is never refined against its images)."""
    if sequence != TRAIN_SEQUENCE:
        return load_params(fit_dir, sequence)
    return read_params(trained_dir / "params.parquet")


def read_params(path: Path) -> dict[str, np.ndarray]:
    """The FLAME/MANO columns of a ``params.parquet``."""
    table = read_table(path, PARAMS)
    return {k: np.asarray(table[k]) for k in PARAM_COLUMNS}


def write_params(path: Path, params: dict[str, np.ndarray]) -> None:
    """``params.parquet`` of T frames (:data:`PARAMS`; the inverse of :func:`read_params`)."""
    num_frames = len(params["flame_global_orient"])
    write_table(path, PARAMS, {"frame": np.arange(num_frames), **{k: params[k] for k in PARAM_COLUMNS}})


def refines_params(cfg: DictConfig, section: DictConfig) -> bool:
    """Whether a training stage (``section``: ``stage.warmup`` or ``stage.dynamic``) refines the train motion's
    parameters (``refine_params``). ``auto``: for parameters a real detector's keypoints were fitted to
    (``fit.source=fitted`` with ``stage.keypoints.detector`` other than ``ground_truth``) or that a dataset provides
    (``fit.source=provided``); not with the ground truth, which has nothing to correct, nor with the synthetic
    ground-truth keypoints, whose fit is finer than what the refinement reaches (measured: their train frames' 3D
    errors grew, hand 1.4 -> 2.0 mm, docs/explanation/tracking-refinement.md); never for SplattingAvatar
    (``method.representation=embedded``: ``true`` is an error there)."""
    value = str(section.refine_params).lower()
    if value not in REFINE_PARAMS:
        raise ValueError(f"refine_params={section.refine_params}: use one of {', '.join(REFINE_PARAMS)}")
    embedded = representation(cfg) == "embedded"
    if value == "auto":
        source = str(cfg.fit.source)
        detected = source == "fitted" and str(cfg.stage.keypoints.detector) != "ground_truth"
        return (detected or source == "provided") and not embedded
    if value == "true" and embedded:
        raise ValueError("refine_params=true: SplattingAvatar (method.representation=embedded) does not refine the "
                         "tracking; set refine_params=auto or false")
    return value == "true"


def param_learning_rates(section: DictConfig) -> ParamLearningRates:
    """The :class:`ParamLearningRates` of a training stage's ``params_lr`` block."""
    return ParamLearningRates(**{f.name: float(getattr(section.params_lr, f.name)) for f in fields(ParamLearningRates)})


def refinement_problems(section: DictConfig) -> list[str]:
    """Range problems of a training stage's ``refine_params`` and ``params_lr``, keyed relative to the stage."""
    problems = [] if str(section.refine_params).lower() in REFINE_PARAMS else \
        [f"refine_params={section.refine_params}: use one of {', '.join(REFINE_PARAMS)}"]
    return problems + [f"params_lr.{p}" for p in param_learning_rates(section).problems()]


@dataclass
class ParamsLrSchema:
    """Types of ``stage.<warmup|dynamic>.params_lr`` (:class:`ParamLearningRates`)."""

    rotation: float
    pose: float
    translation: float
    expression: float


def record_refinement(ctx: StageContext, fitted: dict[str, np.ndarray], trained_on: dict[str, np.ndarray],
                      params: FrameParams | None) -> None:
    """Write the stage's ``params.parquet``: the train motion as this stage left it (``params`` refined here, or
    ``trained_on`` unchanged when None), and the manifest's summary of how far it lies from the fit's ``fitted``
    (``params_refined``: whether this stage refined; ``params_moved_<part>_mm_mean``/``_max``: mean vertex
    displacement per frame; ``params_rotated_<part>_deg_max``)."""
    after = params.arrays() if params is not None else trained_on
    write_params(ctx.out_dir / "params.parquet", after)
    ctx.metrics["params_refined"] = params is not None
    head, hand = templates(ctx.cfg.model)
    moved = parameter_movement(fitted, after, head, hand)
    for part in ("face", "hand"):
        ctx.metrics[f"params_moved_{part}_mm_mean"] = float(np.mean(moved["moved_mm"][part]))
        ctx.metrics[f"params_moved_{part}_mm_max"] = float(np.max(moved["moved_mm"][part]))
        ctx.metrics[f"params_rotated_{part}_deg_max"] = float(np.max(moved["rotated_deg"][part]))


def frame_params(cfg: DictConfig, section: DictConfig, posed: PosedSequence) -> FrameParams | None:
    """The train motion's parameters to refine while training (:class:`FrameParams`), or None when
    :func:`refines_params` says no."""
    if not refines_params(cfg, section):
        return None
    head, hand = templates(cfg.model)
    return FrameParams(posed.params, head, hand, torch.from_numpy(posed.offsets), param_learning_rates(section),
                       centred=bool(section.params_centred))


def load_face_offsets(pbd_dir: Path, sequence: str, num_frames: int, num_vertices: int) -> np.ndarray:
    """(T, V, 3) contact offsets of the face from the pbd stage's ``deform.parquet``: world frame, metres,
    *added* to the posed face (DECAF's canonical, subtracted offsets are converted when imported)."""
    path = pbd_dir / sequence / "deform.parquet"
    offsets = np.asarray(read_table(path, DEFORM)["offsets"], dtype=np.float64)
    if offsets.shape != (num_frames, num_vertices * 3):
        raise SchemaError(f"{path}: offsets of shape {offsets.shape}, expected ({num_frames}, {num_vertices * 3}) "
                          f"for {num_frames} frames of a {num_vertices}-vertex head; rerun the pbd stage")
    return offsets.reshape(num_frames, num_vertices, 3)


def load_views(capture_dir: Path, frames_dir: Path, sequence: str, split: str) -> ViewSet:
    """The crops of ``sequence`` seen by the cameras of ``split`` (``train`` or ``test``)."""
    index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    cameras = {c.camera_id: c for c in read_cameras(capture_dir / "cameras.parquet") if c.split == split}
    rows = [i for i, (seq, cam) in enumerate(zip(index["sequence"], index["camera_id"]))
            if seq == sequence and cam in cameras]
    if not rows:
        raise SchemaError(f"{frames_dir / 'index.parquet'}: no crops of sequence '{sequence}' for split '{split}'")
    camera_ids = sorted(cameras)
    frames = sorted({int(index["frame"][i]) for i in rows})
    K = {index["camera_id"][i]: index["K"][i].reshape(3, 3) for i in rows}
    images = np.stack([np.stack([read_png(rgb_path(frames_dir, sequence, c, t), 3) for c in camera_ids])
                       for t in frames])
    labels = np.stack([np.stack([read_png(crop_mask_path(frames_dir, sequence, c, t), 1) for c in camera_ids])
                       for t in frames])
    background = images[labels == 0].reshape(-1, 3).astype(np.float64).mean(0) / 255.0 \
        if (labels == 0).any() else np.zeros(3)
    return ViewSet(
        images=torch.from_numpy(images),
        labels=torch.from_numpy(labels),
        K=torch.tensor(np.stack([K[c] for c in camera_ids]), dtype=torch.float32),
        world_to_cam=torch.tensor(np.stack([cameras[c].world_to_cam for c in camera_ids]), dtype=torch.float32),
        camera_ids=camera_ids,
        background=torch.tensor(background, dtype=torch.float32),
    )


def load_gaussians(warmup_dir: Path, part_names: tuple[str, ...]) -> BoundGaussians:
    """The trained model from ``gaussians.parquet`` (parts mapped to indices of ``part_names``)."""
    path = warmup_dir / "gaussians.parquet"
    t = read_table(path, BOUND_GAUSSIANS)
    unknown = sorted(set(t["part"]) - set(part_names))
    if unknown:
        raise SchemaError(f"{path}: Gaussians bound to unknown mesh part(s) {unknown}; expected {part_names}")
    as_tensor = lambda name: torch.tensor(np.asarray(t[name]), dtype=torch.float32)  # noqa: E731
    return BoundGaussians(
        local_means=as_tensor("local_means"), log_scales=as_tensor("log_scales"), quats=as_tensor("quats"),
        opacity_logits=as_tensor("opacity_logits"), sh_dc=as_tensor("sh_dc"),
        binding=torch.tensor(np.array(t["binding"])),
        part=torch.tensor([part_names.index(p) for p in t["part"]]),
    )


def driver_subject(cfg: DictConfig) -> str | None:
    """The other subject ``reenact.driver`` names, or ``None`` (``self`` or a parameter file)."""
    driver = str(cfg.reenact.driver)
    return None if driver == "self" or is_parameter_file(driver) else driver


def is_parameter_file(driver: str) -> bool:
    """Whether ``reenact.driver`` names a ``params.parquet`` file rather than ``self`` or a subject."""
    return driver.endswith(".parquet") or "/" in driver


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


def drive(cfg: DictConfig, params: dict[str, np.ndarray], scene: SceneDecision, head_scale: float = 1.0
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
        deform = simulate_sequence(face_v, hand_v, torch.tensor(np.array(head.faces)),
                                   torch.tensor(np.array(hand.faces)), stiffness, solver)
        offsets, frames = deform.offsets, deform.frames
    else:
        offsets, frames, stiffness_source = np.zeros(face_v.shape), [], None
    meshes = posed_meshes(params, head, hand)
    meshes.vertices[:, :head.num_vertices] += torch.from_numpy(offsets).to(meshes.vertices.dtype)
    cond = sequence_conditioning(params, head, hand, torch.from_numpy(offsets))
    return DrivenSequence(params, meshes, cond, offsets, frames, head_scale, stiffness_source)


def transferred_params(cfg: DictConfig, target_fit_dir: Path, driver: dict[str, np.ndarray], source: Path
                       ) -> MotionTransfer:
    """The driver's motion on the target whose fit is ``target_fit_dir`` (its train sequence's identity), placed
    as ``reenact.placement`` says; one error naming ``source`` when the driver cannot drive it."""
    placement = str(cfg.reenact.placement)
    if placement not in PLACEMENTS:
        raise SchemaError(f"reenact.placement={placement}: use one of {', '.join(PLACEMENTS)}")
    head, hand = templates(cfg.model)
    try:
        return transfer_motion(load_params(target_fit_dir, "train"), driver, head, hand, placement)
    except MotionTransferError as exc:
        raise SchemaError(f"{source}: cannot drive the avatar: {exc}") from exc


def transfer_summary(frames: list[dict]) -> dict[str, float]:
    """Manifest metrics of a contact-preserving transfer's per-frame report (empty for the scaled placement):
    frames whose driver's hand touches its face, the fraction of the touching points that touch the target's face
    too, and their mean residual distance from the same surface points (mm, over the touching frames)."""
    if not frames:
        return {}
    touching = [f for f in frames if f["touching_points"]]
    return {"transfer_touch_frames": len(touching),
            "transfer_kept_fraction": (sum(f["kept_points"] for f in touching)
                                       / max(1, sum(f["touching_points"] for f in touching))),
            "transfer_residual_mm": float(np.mean([f["residual_mm"] for f in touching])) if touching else 0.0}


REPRESENTATIONS = ("bound", "embedded")


def representation(cfg: DictConfig) -> str:
    """``method.representation``: ``bound`` (GaussianAvatars' binding; InteractAvatar) or ``embedded``
    (SplattingAvatar)."""
    value = str(cfg.method.representation)
    if value not in REPRESENTATIONS:
        raise ValueError(f"method.representation={value}: use one of {', '.join(REPRESENTATIONS)}")
    return value


def splatting_config(cfg: DictConfig, steps: int, schedule: DictConfig, *, densify: bool) -> SplattingConfig:
    """SplattingAvatar's training settings: its recipe (``splatting.*``), the stage's schedule, seed and
    rasterizer (``schedule``: ``stage.warmup`` or ``stage.dynamic``); ``densify=False`` for stage two."""
    recipe, warm = cfg.splatting, cfg.stage.warmup
    return SplattingConfig(
        steps=steps, lambda_mse=float(recipe.lambda_mse), lambda_lpips=float(recipe.lambda_lpips),
        scale_weight=float(recipe.scale_weight), walk_every=int(recipe.walk_every),
        densify_until=float(warm.densify_until) if densify else 0.0,
        opacity_reset_interval=float(warm.opacity_reset_interval), max_gaussians=int(warm.max_gaussians),
        checkpoint_every=int(schedule.checkpoint_every), log_every=int(schedule.log_every),
        seed=int(schedule.seed), backend=str(schedule.backend))


@dataclass
class FlatStopSchema:
    """Types of ``stage.<warmup|dynamic>.validation.stop_when_flat``."""

    enabled: bool
    min_gain_db: float
    window: int


@dataclass
class ValidationSchema:
    """Types of ``stage.<warmup|dynamic>.validation`` (docs/how-to/quality-during-training.md)."""

    every: int
    frames: int
    lpips: bool
    stop_when_flat: FlatStopSchema


def validation_config(conf: DictConfig) -> ValidationConfig:
    """The training loops' :class:`ValidationConfig` of a ``stage.<warmup|dynamic>.validation`` block."""
    stop = conf.stop_when_flat
    return ValidationConfig(int(conf.every), int(conf.frames), bool(conf.lpips),
                            FlatStop(bool(stop.enabled), float(stop.min_gain_db), int(stop.window)))


def validation_problems(conf: DictConfig) -> list[str]:
    """Range problems of a stage section's ``validation`` block, keyed relative to the section."""
    return [f"validation.{problem}" for problem in validation_config(conf.validation).problems()]


def record_validation(ctx: StageContext, validator: Validator) -> None:
    """Write ``curve.parquet`` (no rows without validation) and the validation metrics of the manifest."""
    write_table(ctx.out_dir / "curve.parquet", CURVE, validator.table())
    ctx.metrics.update(validator.metrics())


@dataclass
class PosedGaussians:
    """World-space Gaussians of one frame (a :class:`WorldGaussians`)."""

    means: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


TrainedModel = DynamicAvatar | EmbeddedGaussians


def load_trained(dynamic_dir: Path) -> TrainedModel:
    """The method's final model from the dynamic stage: mesh-bound (with or without the MLPs) or, for
    ``method.representation=embedded``, SplattingAvatar's embedded Gaussians (``model.json`` says which)."""
    info = json.loads((dynamic_dir / "model.json").read_text())
    if info.get("representation", "bound") == "embedded":
        state = torch.load(dynamic_dir / "networks.pt", weights_only=True)
        return load_embedded_gaussians(dynamic_dir, tuple(info["part_names"]), state["canonical_vertices"],
                                       state["faces"])
    return load_dynamic(dynamic_dir)


def posed_gaussians(model: TrainedModel, cond: SequenceConditioning, vertices: torch.Tensor,
                    frame: int) -> WorldGaussians:
    """The model's Gaussians on frame ``frame`` of a sequence (``vertices`` (V, 3) its posed meshes), as
    evaluated (the dynamic model's most probable PointNet++ sample)."""
    if isinstance(model, EmbeddedGaussians):
        means, scales, quats = model.world(vertices, model.mesh.faces)
        return PosedGaussians(means, scales, quats, model.opacities(), model.colors())
    return model(cond.frame(frame), vertices)


def write_embedded_gaussians(path: Path, model: EmbeddedGaussians, part_names: tuple[str, ...]) -> None:
    """``gaussians.parquet`` of SplattingAvatar's embedded Gaussians (:data:`EMBEDDED_GAUSSIANS`)."""
    state = model.state_tensors()
    write_table(path, EMBEDDED_GAUSSIANS, {
        **{k: state[k].numpy() for k in ("triangle", "barycentric", "displacement", "log_scales", "quats",
                                         "opacity_logits", "sh_dc")},
        "part": [part_names[i] for i in state["part"].tolist()],
    })


def load_embedded_gaussians(stage_dir: Path, part_names: tuple[str, ...], canonical_vertices: torch.Tensor,
                            faces: torch.Tensor) -> EmbeddedGaussians:
    """The embedded Gaussians of ``gaussians.parquet`` on the canonical mesh (``canonical_vertices`` (V, 3),
    ``faces`` (F, 3))."""
    path = stage_dir / "gaussians.parquet"
    t = read_table(path, EMBEDDED_GAUSSIANS)
    unknown = sorted(set(t["part"]) - set(part_names))
    if unknown:
        raise SchemaError(f"{path}: Gaussians on unknown mesh part(s) {unknown}; expected {part_names}")
    state = {k: torch.tensor(np.asarray(t[k]), dtype=torch.float32) for k in
             ("barycentric", "displacement", "log_scales", "quats", "opacity_logits", "sh_dc")}
    state["triangle"] = torch.tensor(np.asarray(t["triangle"]))
    state["part"] = torch.tensor([part_names.index(p) for p in t["part"]])
    try:
        return EmbeddedGaussians.from_state_tensors(state, canonical_vertices.float(), faces)
    except ValueError as exc:
        raise SchemaError(f"{path}: {exc}; rerun the stage that wrote it") from exc


def load_dynamic(dynamic_dir: Path) -> DynamicAvatar:
    """The dynamic stage's trained model (``model.json``, ``gaussians.parquet``, ``networks.pt``)."""
    info = json.loads((dynamic_dir / "model.json").read_text())
    part_names = tuple(info["part_names"])
    gaussians = load_gaussians(dynamic_dir, part_names)
    arch = info["architecture"]
    cfg = DynamicModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in arch.items()})
    state = torch.load(dynamic_dir / "networks.pt", weights_only=True)
    model = DynamicAvatar(gaussians, state["mu_cano"], state["faces"], part_names, int(info["num_face_vertices"]),
                          info["frame_dims"], cfg)
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("gaussians.")]
    if missing or unexpected:
        raise SchemaError(f"{dynamic_dir / 'networks.pt'}: does not match model.json (missing {missing[:3]}, "
                          f"unexpected {unexpected[:3]}); rerun the dynamic stage")
    return model


def write_bound_gaussians(path: Path, model: BoundGaussians, part_names: tuple[str, ...]) -> None:
    """``gaussians.parquet`` of ``model`` (the inverse of :func:`load_gaussians`)."""
    with torch.no_grad():
        write_table(path, BOUND_GAUSSIANS, {
            "binding": model.binding.numpy(),
            "part": [part_names[i] for i in model.part.tolist()],
            "local_means": model.local_means.numpy(),
            "log_scales": model.log_scales.numpy(),
            "quats": model.quats.numpy(),
            "opacity_logits": model.opacity_logits.numpy(),
            "sh_dc": model.sh_dc.numpy(),
        })


def write_frame_ply(path: Path, g: WorldGaussians) -> None:
    """World-space 3DGS PLY of one frame's Gaussians (``means``, ``scales``, ``quats``, ``opacities``,
    ``colors`` attributes, e.g. an :class:`avatar.dynamic.DynamicFrame`)."""
    with torch.no_grad():
        o = g.opacities.clamp(1e-6, 1 - 1e-6)
        write_gaussians_ply(path, GaussianCloud.from_rgb(
            g.means.numpy(), torch.log(g.scales).numpy(), g.quats.numpy(), torch.log(o / (1 - o)).numpy(),
            g.colors.numpy()))


def model_files(cfg: DictConfig) -> list[Path]:
    """The official FLAME/MANO files the config names (``model.*_path``), for source hashing."""
    return [Path(p).resolve() for p in (cfg.model.flame_path, cfg.model.mano_path) if p and Path(p).is_file()]


def unused_solver_settings(cfg: DictConfig) -> tuple[str, ...]:
    """The ``stage.pbd.solver`` settings the chosen solver never reads (``unused_keys`` of the pbd stage)."""
    return tuple(f"stage.pbd.solver.{name}" for name in unused_pbd_settings(str(cfg.stage.pbd.solver.method)))


def unused_driving_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What of ``stage.pbd.solver`` a stage that drives the avatar (:func:`drive`) never reads: all of it for a
    method without PBD, else the settings of the solvers not chosen."""
    return unused_solver_settings(cfg) if bool(cfg.method.pbd) else ("stage.pbd.solver",)


def unused_training_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What the training stages never read for this method: SplattingAvatar's recipe (``splatting``) unless the
    method's representation is ``embedded``."""
    return () if representation(cfg) == "embedded" else ("splatting",)


def pbd_solver_config(cfg: DictConfig) -> PBDConfig:
    """The XPBD solver's settings of ``stage.pbd.solver`` (one clear error when out of range)."""
    try:
        return PBDConfig(**OmegaConf.to_container(cfg.stage.pbd.solver, resolve=True))
    except ValueError as exc:
        raise SchemaError(f"stage.pbd.solver: {exc}") from exc


def face_stiffness(cfg: DictConfig, head: TemplateModel, solver: PBDConfig) -> tuple[torch.Tensor, str]:
    """(V,) relative attachment stiffness of the face and where it came from (``model.face_stiffness_path``,
    the template's skin-to-skull distance, or a uniform estimate)."""
    try:
        rel, source = face_relative_stiffness(head.num_vertices, head.inner_distance,
                                              cfg.model.get("face_stiffness_path"), solver.reference_thickness_m,
                                              solver.stiffness_power)
    except StiffnessFileError as exc:
        raise SchemaError(f"model.face_stiffness_path: {exc}") from exc
    return torch.from_numpy(rel), source


def contact_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # noqa: ARG001 - the SourceLister signature
    """Source lister of stages that simulate contact: the official model files and the face stiffness file."""
    stiffness = cfg.model.get("face_stiffness_path")
    extra = [Path(stiffness).resolve()] if stiffness and Path(stiffness).is_file() else []
    return SourceFiles(Path("/"), tuple(model_files(cfg) + extra))


def model_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # noqa: ARG001 - the SourceLister signature
    """Source lister of stages that pose the official models: a replaced model file reruns them."""
    return SourceFiles(Path("/"), tuple(model_files(cfg)))


def load_scene(scene_dir: Path) -> SceneDecision:
    """The scene stage's decisions (``scene.json``): what the downstream stages model, and why."""
    info = json.loads((scene_dir / "scene.json").read_text())
    return SceneDecision(bool(info["model_hand"]), bool(info["model_pbd"]), bool(info["model_interaction"]),
                         dict(info["why"]))
