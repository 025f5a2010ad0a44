"""Stage ``dynamic``: stage two of the paper, the hand MLPs H, the interaction MLPs I and PointNet++ on top
of the warm-up Gaussians (docs/explanation/dynamic-model.md), trained by the method's representation
(:mod:`avatar.representations`; SplattingAvatar's continues its own recipe).

For the bound representation it writes ``gaussians.parquet`` (the fine-tuned Gaussians, the warm-up's schema),
``networks.pt`` (a torch state dict of the MLPs, PointNet++, the point features and the canonical positions; load
it with ``torch.load(..., weights_only=True)``), ``model.json`` (the representation's name, the architecture and
the conditioning widths: everything needed to rebuild the model around the two), ``train_log.parquet`` and
world-space 3DGS PLYs of the frames ``stage.dynamic.ply_frames`` asks for (``ply/train_<frame>.ply``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from omegaconf import DictConfig

from avatar.artifacts import TRAIN_SEQUENCE, load_views, method_params
from avatar.artifacts.dependencies import TEMPLATE_KEYS, model_sources
from avatar.artifacts.motion import applied_deformation, posed_sequence
from avatar.representations import (
    VALIDATED_RUN,
    representation,
    representation_problems,
    training_settings,
    unused_stage_two_settings,
)
from avatar.representations.bound.dynamic_model import DynamicModelConfig
from avatar.representations.bound.representation import PRESET_ARCHITECTURE, selection_config
from avatar.representations.bound.stage_two import DynamicTrainConfig
from avatar.training.frame_params import ParamLearningRates
from avatar.training.selection import SelectionConfig
from avatar.training.settings import ValidationSchema, refinement_problems, validation_problems
from data_schemas.config_sections import core_config, section_schema
from pipeline.stage import StageContext, stage


@dataclass
class SelectSchema:
    """Types of ``stage.dynamic.select`` (:class:`avatar.training.selection.SelectionConfig`)."""

    enabled: bool
    margin_db: float


@dataclass
class DynamicStageSettings:
    """Stage two's own settings: those neither the model's :class:`DynamicModelConfig` nor the training loop's
    :class:`DynamicTrainConfig` holds."""

    ply_frames: list[int]
    refine_params: str
    params_lr: ParamLearningRates
    params_centred: bool
    select: SelectSchema
    restarts: int
    validation: ValidationSchema

    @classmethod
    def validate(cls, conf: DictConfig) -> list[str]:
        """Range problems of a ``stage.dynamic`` section, one line each; empty when it can run."""
        problems = []
        # the loop's and the model's own ranges (their size and steps are the preset's, not checked here)
        problems += core_config(DynamicTrainConfig, conf, steps=1, selection=SelectionConfig()).problems()
        sizes = {f.name: f.default for f in fields(DynamicModelConfig) if f.name in PRESET_ARCHITECTURE}
        problems += core_config(DynamicModelConfig, conf, **sizes).problems()
        select = selection_config(conf)
        problems += [f"select.{problem}" for problem in select.problems()]
        if select.enabled and int(conf.validation.every) <= 0:
            problems.append(
                "select.enabled=true needs validation frames: set stage.dynamic.validation.every > 0 "
                "(e.g. 50), or select.enabled=false"
            )
        if int(conf.restarts) < 1:
            problems.append(
                f"restarts={conf.restarts}: must be >= 1 (stage two's initialisations, the best on validation kept)"
            )
        return problems + validation_problems(conf) + refinement_problems(conf)


#: The settings of ``stage.dynamic`` that the model's :class:`DynamicModelConfig` holds (its widths and depths come
#: from the quality preset) and the stage's own.
DynamicSettings = section_schema(
    "DynamicSettings", DynamicModelConfig, exclude=PRESET_ARCHITECTURE, own=DynamicStageSettings
)

#: Types of ``stage.dynamic`` (values in conf/stage/dynamic.yaml): every hyperparameter of the training loop's
#: :class:`DynamicTrainConfig` (its steps come from ``quality.dynamic_steps``, its selection from ``select``), of
#: the model's :class:`DynamicModelConfig` but its size, and the stage's own settings.
DynamicConfig = section_schema("DynamicConfig", DynamicTrainConfig, exclude=("steps", "selection"), own=DynamicSettings)


@stage(
    "dynamic",
    inputs=("capture", "frames", "fit", "scene", "pbd", "warmup"),
    config_keys=(
        "quality.dynamic_steps",
        "quality.dynamic_width",
        "quality.dynamic_hand_depth",
        "quality.dynamic_interaction_depth",
        "quality.geometry_feature_dim",
        "quality.pointnet_width",
        "quality.pointnet_centres",
        *TEMPLATE_KEYS,
        "stage.dynamic",
        "method.representation",
        "method.pbd",
        "stage.warmup",
        "fit.source",
        "stage.keypoints.detector",
    ),  # refines_params
    outputs=(
        "gaussians.parquet",
        "networks.pt",
        "model.json",
        "train_log.parquet",
        "ply",
        "curve.parquet",
        "params.parquet",
    ),
    # 14: I is judged only when a withheld frame has contact (selection_judged_*); 12: validation.fraction,
    # min_train_frames, retrain (choose on withheld frames, then train on every frame),
    # restarts, the contact emphasis cap instead of max_contact_frame_share; 11: model.json names the representation
    # (the registry loads the model by it); 10: issue 33's faster step
    # (fused layers, fused Adam; rounding-level changes); 9: refine_params, stage two posed from the warm-up's
    # params.parquet; 8: stage.dynamic.select (the kept step and modules); 7: SSIM filtered by
    # shifted sums instead of conv2d (rounding-level changes); 6: the compiled rasterizer's alpha as a power of two
    # (rounding-level)
    version="14",
    device=True,
    precision=True,
    per_method=True,
    config_schema=DynamicConfig,
    # resuming is bit-for-bit: it cannot change the result
    cache_exclude=("stage.dynamic.checkpoint_every", "stage.warmup.checkpoint_every"),
    extra_keys=training_settings,  # the representation's own recipe (SplattingAvatar's splatting, a plug-in's)
    unused_keys=unused_stage_two_settings,  # e.g. restarts without the selection, validation's details without it
    checks=representation_problems,
    sources=model_sources,
)
def dynamic(ctx: StageContext) -> None:
    """Stage two on every train camera and frame: H, I, PointNet++, the point features and the Gaussians
    (the ablations and GaussianAvatars: what of it the method keeps), or SplattingAvatar trained on. With
    ``stage.dynamic.validation.every`` > 0 it withholds ``validation.fraction`` of the train frames (as far as
    ``validation.min_train_frames`` stay), validates on them, may stop early (``curve.parquet``;
    docs/how-to/quality-during-training.md) and selects (``select``, best of ``restarts`` initialisations); with
    ``validation.retrain`` the model written then trains on every frame with what was chosen
    (docs/explanation/selection.md). The train motion is posed with the
    warm-up's ``params.parquet`` and, with ``stage.dynamic.refine_params``, refined further; ``params.parquet`` holds
    it as trained on, which ``evaluate``, ``reenact`` and the PLY export pose the train motion with."""
    conf = ctx.cfg.stage.dynamic
    torch.manual_seed(conf.seed)
    fit_dir, pbd_dir, warmup_dir = ctx.input_dir("fit"), ctx.input_dir("pbd"), ctx.input_dir("warmup")
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), "train", "train", ctx.device)
    deformation = applied_deformation(ctx.cfg, pbd_dir)
    posed = posed_sequence(
        fit_dir, TRAIN_SEQUENCE, ctx.cfg, deformation, method_params(warmup_dir, fit_dir, TRAIN_SEQUENCE)
    )
    validated = None
    if (warmup_dir / VALIDATED_RUN).is_dir():  # the warm-up trained again on every frame after its validated run
        validated = posed_sequence(
            fit_dir,
            TRAIN_SEQUENCE,
            ctx.cfg,
            deformation,
            method_params(warmup_dir / VALIDATED_RUN, fit_dir, TRAIN_SEQUENCE),
        )
    representation(ctx.cfg).train(ctx, views, posed, validated)
