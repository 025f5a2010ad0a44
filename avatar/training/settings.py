"""Settings the two training stages share: the refinement of the train motion's parameters (``refine_params``,
``params_lr``) and the validation during training (``validation``), with their schemas, range checks and records."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import write_params
from avatar.artifacts.motion import PosedSequence, templates
from avatar.artifacts.stage_run import StageRun
from avatar.training.frame_params import FrameParams, ParamLearningRates, parameter_movement
from avatar.training.validation import FlatStop, ValidationConfig, Validator, withheld_count
from data_schemas.curve import CURVE
from data_schemas.tables import write_table

REFINE_PARAMS = ("auto", "true", "false")


def refines_params(cfg: DictConfig, section: DictConfig, can_refine: bool) -> bool:
    """Whether a training stage (``section``: ``stage.warmup`` or ``stage.dynamic``) refines the train motion's
    parameters (``refine_params``). ``auto``: for parameters a real detector's keypoints were fitted to
    (``fit.source=fitted`` with ``stage.keypoints.detector`` other than ``ground_truth``) or that a dataset provides
    (``fit.source=provided``); not with the ground truth, which has nothing to correct, nor with the synthetic
    ground-truth keypoints, whose fit is finer than what the refinement reaches (measured: their train frames' 3D
    errors grew, hand 1.4 -> 2.0 mm, docs/explanation/tracking-refinement.md); never for a representation that
    cannot (``can_refine``: the method's :attr:`Representation.refines_tracking`, false for SplattingAvatar's;
    ``true`` is an error there)."""
    value = str(section.refine_params).lower()
    if value not in REFINE_PARAMS:
        raise ValueError(f"refine_params={section.refine_params}: use one of {', '.join(REFINE_PARAMS)}")
    if value == "auto":
        source = str(cfg.fit.source)
        detected = source == "fitted" and str(cfg.stage.keypoints.detector) != "ground_truth"
        return (detected or source == "provided") and can_refine
    if value == "true" and not can_refine:
        raise ValueError(
            f"refine_params=true: method.representation={cfg.method.representation} does not refine "
            f"the tracking; set refine_params=auto or false"
        )
    return value == "true"


def param_learning_rates(section: DictConfig) -> ParamLearningRates:
    """The :class:`ParamLearningRates` of a training stage's ``params_lr`` block."""
    return ParamLearningRates(**{f.name: float(getattr(section.params_lr, f.name)) for f in fields(ParamLearningRates)})


def refinement_problems(section: DictConfig) -> list[str]:
    """Range problems of a training stage's ``refine_params`` and ``params_lr``, keyed relative to the stage."""
    problems = (
        []
        if str(section.refine_params).lower() in REFINE_PARAMS
        else [f"refine_params={section.refine_params}: use one of {', '.join(REFINE_PARAMS)}"]
    )
    return problems + [f"params_lr.{p}" for p in param_learning_rates(section).problems()]


def record_refinement(
    ctx: StageRun, fitted: dict[str, np.ndarray], trained_on: dict[str, np.ndarray], params: FrameParams | None
) -> None:
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


def frame_params(
    cfg: DictConfig, section: DictConfig, posed: PosedSequence, can_refine: bool, device: torch.device | str = "cpu"
) -> FrameParams | None:
    """The train motion's parameters to refine while training (:class:`FrameParams`, on ``device``), or None when
    :func:`refines_params` says no (``can_refine``: whether the method's representation can)."""
    if not refines_params(cfg, section, can_refine):
        return None
    head, hand = templates(cfg.model)
    return FrameParams(
        posed.params,
        head,
        hand,
        torch.from_numpy(posed.offsets),
        param_learning_rates(section),
        centred=bool(section.params_centred),
        device=device,
    )


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
    fraction: float
    min_train_frames: int
    retrain: bool
    lpips: bool
    stop_when_flat: FlatStopSchema


def unused_section_settings(cfg: DictConfig, stage: str, can_refine: bool) -> tuple[str, ...]:
    """What a training stage never reads of ``stage.<stage>`` (``warmup``, ``dynamic``) in the configuration ``cfg``:
    ``validation``'s details with validation off (``validation.every`` <= 0: no frame withheld, none validated on),
    ``params_lr`` and ``params_centred`` where it refines no parameters (:func:`refines_params`; ``can_refine``:
    whether the method's representation can), and stage two's ``restarts`` and ``select.margin_db`` without the
    selection (``select.enabled`` with validation on). Left out of the stages' cache keys (``unused_keys``)."""
    section, name = cfg.stage[stage], f"stage.{stage}"
    validating = int(section.validation.every) > 0
    unused = (
        [] if validating else [f"{name}.validation.{f.name}" for f in fields(ValidationSchema) if f.name != "every"]
    )
    try:
        refining = refines_params(cfg, section, can_refine)
    except ValueError:  # refused by the config check before any key is computed
        refining = True
    if not refining:
        unused += [f"{name}.params_lr", f"{name}.params_centred"]
    if stage == "dynamic" and not (validating and bool(section.select.enabled)):
        unused += [f"{name}.restarts", f"{name}.select.margin_db"]
    return tuple(unused)


def validation_config(conf: DictConfig, num_frames: int) -> ValidationConfig:
    """The training loops' :class:`ValidationConfig` of a ``stage.<warmup|dynamic>.validation`` block for a training
    sequence of ``num_frames`` frames: ``fraction`` of them withheld, as far as ``min_train_frames`` stay to train on
    (:func:`withheld_count`)."""
    stop = conf.stop_when_flat
    on = int(conf.every) > 0 and num_frames > 0
    frames = withheld_count(num_frames, float(conf.fraction), int(conf.min_train_frames)) if on else 0
    return ValidationConfig(
        int(conf.every),
        frames,
        bool(conf.lpips),
        FlatStop(bool(stop.enabled), float(stop.min_gain_db), int(stop.window)),
    )


def validation_problems(conf: DictConfig) -> list[str]:
    """Range problems of a stage section's ``validation`` block, keyed relative to the section."""
    block = conf.validation
    problems = [f"validation.{problem}" for problem in validation_config(block, 0).problems()]
    fraction = float(block.fraction)
    if not 0.0 < fraction < 1.0:  # also refuses NaN
        problems.append(
            f"validation.fraction={fraction:g}: must lie strictly between 0 and 1 (the share of the training frames "
            "withheld for validation, e.g. 0.15)"
        )
    if int(block.min_train_frames) < 1:
        problems.append(
            f"validation.min_train_frames={block.min_train_frames}: must be >= 1 (training frames that stay to train "
            "on)"
        )
    return problems


def retrains(conf: DictConfig, validator: Validator) -> bool:
    """Whether a training stage (``conf``: ``stage.warmup`` or ``stage.dynamic``) trains again on every training frame
    after its validated run (``validation.retrain``, and frames were withheld)."""
    return bool(conf.validation.retrain) and validator.cfg.enabled


def record_validation(ctx: StageRun, validator: Validator, final_frames: int) -> None:
    """Write ``curve.parquet`` (no rows without validation) and the validation metrics of the manifest:
    ``validation_frames_withheld`` (by the validated run) and ``final_training_frames`` (the frames the written
    model trained on: all of them after a retrain)."""
    write_table(ctx.out_dir / "curve.parquet", CURVE, validator.table())
    ctx.metrics.update(validator.metrics())
    ctx.metrics["validation_frames_withheld"] = int(validator.frames.size)
    ctx.metrics["final_training_frames"] = int(final_frames)
