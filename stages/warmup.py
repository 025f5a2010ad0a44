"""Stage ``warmup``: stage one, static Gaussians on the FLAME and MANO triangles in the method's representation
(:mod:`avatar.representations`; bound to them for GaussianAvatars and InteractAvatar)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from avatar.artifacts import TRAIN_SEQUENCE, PosedGaussians, load_scene, load_views, write_frame_ply, write_params
from avatar.artifacts.dependencies import TEMPLATE_KEYS, model_sources
from avatar.artifacts.motion import PosedSequence, applied_deformation, posed_sequence
from avatar.geometry.views import ViewSet
from avatar.render.gaussians import resolve_backend
from avatar.representations import (
    VALIDATED_RUN,
    CanonicalGaussians,
    representation,
    representation_problems,
    run_scratch,
    training_settings,
    unused_warmup_settings,
)
from avatar.representations.bound.warmup import WarmupTrainConfig, colors_from_views
from avatar.training.frame_params import FrameParams, ParamLearningRates
from avatar.training.settings import (
    ValidationSchema,
    frame_params,
    record_refinement,
    record_validation,
    refinement_problems,
    retrains,
    validation_config,
    validation_problems,
)
from avatar.training.validation import ValidationConfig, Validator
from data_schemas.capture import MASK_LABELS
from data_schemas.config_sections import section_schema
from pipeline.stage import StageContext, stage


@dataclass
class WarmupSettings:
    """The warm-up's own settings: those the training loop's :class:`WarmupTrainConfig` does not hold."""

    init_opacity: float
    ply_frame: int
    refine_params: str
    params_lr: ParamLearningRates
    params_centred: bool
    validation: ValidationSchema

    def __post_init__(self) -> None:
        problems = self.validate(self)
        if problems:
            raise ValueError("; ".join(problems))

    @classmethod
    def validate(cls, conf: Any) -> list[str]:
        """Range problems of a ``stage.warmup`` section (this dataclass or the DictConfig merged onto it),
        one line each, keyed relative to ``stage.warmup``; empty when it can run."""
        problems = []
        opacity = float(conf.init_opacity)
        if not 0.0 < opacity < 1.0:  # also refuses NaN
            problems.append(
                f"init_opacity={opacity:g}: must lie strictly between 0 and 1 (the opacity logit is "
                f"infinite at 0 and 1); use e.g. 0.1, the 3DGS default"
            )
        return problems + validation_problems(conf) + refinement_problems(conf)


#: Types of ``stage.warmup`` (values in conf/stage/warmup.yaml): every hyperparameter of the training loop's
#: :class:`WarmupTrainConfig` (its steps come from ``quality.warmup_steps``) and the stage's own settings.
WarmupConfig = section_schema("WarmupConfig", WarmupTrainConfig, exclude=("steps",), own=WarmupSettings)


@stage(
    "warmup",
    inputs=("capture", "frames", "fit", "scene", "pbd"),
    config_keys=(
        "quality.gaussians_per_triangle",
        "quality.warmup_steps",
        *TEMPLATE_KEYS,
        "stage.warmup",
        "method.representation",
        "method.pbd",
        "fit.source",
        "stage.keypoints.detector",
    ),
    outputs=("gaussians.parquet", "gaussians.ply", "train_log.parquet", "curve.parquet", "params.parquet"),
    version="10",
    device=True,
    # 10: validation.fraction/min_train_frames/retrain (the validated run in validation/, then every frame);
    # 9: gaussians.ply by the one PLY writer (write_frame_ply: opacity logits of the clamped opacities, equal to
    # rounding); 8: refine_params (the train motion's parameters refined with the Gaussians; params.parquet);
    # 7: SSIM filtered by shifted sums instead of conv2d (rounding-level changes); 6: the compiled
    # rasterizer's alpha as a power of two (rounding-level)
    per_method=True,
    config_schema=WarmupConfig,
    cache_exclude=("stage.warmup.checkpoint_every",),  # resuming is bit-for-bit: it cannot change the result
    extra_keys=training_settings,  # the representation's own recipe (SplattingAvatar's splatting, a plug-in's)
    unused_keys=unused_warmup_settings,  # e.g. validation's details with validation off
    checks=representation_problems,
    sources=model_sources,
)
def warmup(ctx: StageContext) -> None:
    """Stage one on every train camera and train frame: static Gaussians in the method's representation (bound to
    the triangles for GaussianAvatars and InteractAvatar's warm-up; SplattingAvatar's embedded Gaussians).
    With ``stage.warmup.validation.every`` > 0 it withholds ``validation.fraction`` of the train frames (as far as
    ``validation.min_train_frames`` stay), validates on them and may stop early (``curve.parquet``;
    docs/how-to/quality-during-training.md); with ``validation.retrain`` it then trains again on every train frame
    for the steps that run took (docs/explanation/selection.md) and keeps the validated run's model in
    ``validation/`` (``gaussians.parquet``, ``params.parquet``), which stage two chooses with. With
    ``stage.warmup.refine_params`` (``auto``: fitted or provided tracking) each step also refines the rendered frame's
    FLAME/MANO parameters (:mod:`avatar.training.frame_params`); ``params.parquet`` holds the train motion's
    parameters as trained on (the fit's where nothing was refined), which stage two starts from."""
    conf = ctx.cfg.stage.warmup
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), "train", "train", ctx.device)
    posed = posed_sequence(
        ctx.input_dir("fit"), TRAIN_SEQUENCE, ctx.cfg, applied_deformation(ctx.cfg, ctx.input_dir("pbd"))
    )
    validator = Validator(validation_config(conf.validation, views.num_frames), views)
    retrain = retrains(conf, validator)
    first_dir = ctx.out_dir / VALIDATED_RUN if retrain else ctx.out_dir
    model, params, final_loss = _train(ctx, views, posed, validator, first_dir, "validated" if retrain else "")
    if retrain:  # the validated run chose the steps; the model written trains them on every frame
        write_params(first_dir / "params.parquet", params.arrays() if params is not None else posed.params)
        final = Validator(ValidationConfig(), views, limit=validator.end)
        model, params, final_loss = _train(ctx, views, posed, final, ctx.out_dir, "final")
    meshes = posed.meshes.to(ctx.device)
    frame = min(int(conf.ply_frame), meshes.vertices.shape[0] - 1)
    with torch.no_grad():
        vertices = params.vertices(frame) if params is not None else meshes.vertices[frame]
        means, scales, quats = model.world(vertices, meshes.faces)
        write_frame_ply(
            ctx.out_dir / "gaussians.ply", PosedGaussians(means, scales, quats, model.opacities(), model.colors())
        )
    record_refinement(ctx, posed.params, posed.params, params)
    ctx.metrics["gaussians"] = model.num_gaussians
    ctx.metrics["final_loss"] = final_loss
    record_validation(ctx, validator, views.num_frames if retrain else int(validator.train_frames.size))
    ctx.metrics["steps"] = validator.end  # steps run
    # backend=auto resolves per machine (compiled where it built, else torch; equal to float32 rounding):
    # the manifest records which one computed this artifact.
    ctx.metrics["rasterizer"] = resolve_backend(conf.backend, means)


def _train(
    ctx: StageContext, views: ViewSet, posed: PosedSequence, validator: Validator, out_dir: Path, run: str
) -> tuple[CanonicalGaussians, FrameParams | None, float]:
    """One warm-up run from scratch on the frames ``validator`` leaves to training, for its steps: the model
    (written to ``out_dir`` by the representation), the refined parameters (None where nothing is refined) and the
    final loss. ``run`` names the run's checkpoint folder in the stage's scratch (``""``: the scratch itself)."""
    conf, q = ctx.cfg.stage.warmup, ctx.cfg.quality
    torch.manual_seed(conf.seed)
    rep = representation(ctx.cfg)
    populate = None  # every triangle; without a hand in the scene, only the face's (a face-only avatar)
    if not load_scene(ctx.input_dir("scene")).model_hand:
        populate = posed.meshes.face_part != posed.meshes.part_names.index("hand")
    # populated on the CPU, where the seed's draws are the same on every machine, then moved to the run's device
    model = rep.populate(
        posed.meshes.vertices[0],  # the paper's canonical frame: the first training frame
        posed.meshes,
        int(q.gaussians_per_triangle),
        init_opacity=conf.init_opacity,
        seed=conf.seed,
        populate=populate,
    ).to(ctx.device)
    meshes, params = posed.meshes.to(ctx.device), frame_params(ctx.cfg, conf, posed, rep.refines_tracking, ctx.device)
    with torch.no_grad():
        means, _, _ = model.world(meshes.vertices[0], meshes.faces)
    part_label = torch.tensor([MASK_LABELS[name] for name in meshes.part_names], device=ctx.device)[model.part]
    model.set_colors(colors_from_views(means, part_label, views, frame=0))
    out_dir.mkdir(exist_ok=True)
    checkpoints = run_scratch(ctx, run)
    desc = f"warmup ({run})" if run else "warmup"
    final_loss = rep.warm_up(
        ctx,
        model,
        views,
        meshes,
        params,
        validator,
        lambda steps: ctx.progress(steps, desc=desc),
        out_dir=out_dir,
        checkpoint_dir=checkpoints,
    )
    return model, params, final_loss
