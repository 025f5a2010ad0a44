"""Stage ``dynamic``: stage two of the paper, the hand MLPs H, the interaction MLPs I and PointNet++ on top
of the warm-up Gaussians (docs/explanation/dynamic-model.md).

Writes ``gaussians.parquet`` (the fine-tuned Gaussians, the warm-up's schema), ``networks.pt`` (a torch
state dict of the MLPs, PointNet++, the point features and the canonical positions; load it with
``torch.load(..., weights_only=True)``), ``model.json`` (the architecture and the conditioning widths:
everything needed to rebuild the model around the two), ``train_log.parquet`` and world-space 3DGS PLYs of
the frames ``stage.dynamic.ply_frames`` asks for (``ply/train_<frame>.ply``).
"""

from __future__ import annotations

import io
import time
from dataclasses import asdict, dataclass

import torch

from avatar.dynamic import DynamicAvatar, DynamicModelConfig
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.dynamic.model import COLOUR_DELTAS
from avatar.posing import MeshSequence
from avatar.render.gaussians import resolve_backend
from avatar.scene import SceneDecision
from avatar.training.data import ViewSet
from avatar.training.dynamic import DynamicTrainConfig, train_dynamic
from avatar.training.selection import SelectionConfig
from avatar.training.splatting import train_splatting
from avatar.training.validation import Validator
from data_schemas.gaussians import DYNAMIC_TRAIN_LOG
from data_schemas.splatting import SPLATTING_TRAIN_LOG
from data_schemas.tables import write_records
from data_schemas.writes import write_bytes, write_json
from pipeline.stage import StageContext, stage
from stages.common import (
    ParamsLrSchema, PosedSequence, TRAIN_SEQUENCE, TrainedModel, ValidationSchema, applied_deformation, contact_flags,
    frame_params, load_embedded_gaussians, load_gaussians, load_params, load_scene, load_sequence, load_views,
    method_params, model_sources, posed_gaussians, posed_sequence, record_refinement, record_validation,
    refinement_problems, representation, splatting_config, templates, unused_training_settings, validation_config,
    validation_problems, write_bound_gaussians, write_embedded_gaussians, write_frame_ply,
)


@dataclass
class SelectSchema:
    """Types of ``stage.dynamic.select`` (:class:`avatar.training.selection.SelectionConfig`)."""

    enabled: bool
    margin_db: float


@dataclass
class DynamicConfig:
    """Types of ``stage.dynamic`` (values in conf/stage/dynamic.yaml)."""

    hand_mlp: bool
    interaction: bool
    lambda_dssim: float
    scale_weight: float
    position_weight: float
    patch_weight: float
    eps_s: float
    eps_mu: float
    lr_mlp: float
    lr_point_features: float
    lr_decay: float
    contact_fraction: float
    max_contact_frame_share: float
    colour_delta: str
    patch_min_size: int
    d_max: float
    deform_threshold_m: float
    position_frequencies: int
    offset_frequencies: int
    point_feature_dim: int
    checkpoint_every: int
    log_every: int
    ply_frames: list[int]
    backend: str
    seed: int
    refine_params: str
    params_lr: ParamsLrSchema
    params_centred: bool
    select: SelectSchema
    validation: ValidationSchema

    @classmethod
    def validate(cls, conf: object) -> list[str]:
        """Range problems of a ``stage.dynamic`` section, one line each; empty when it can run."""
        problems = []
        fraction = float(conf.contact_fraction)  # type: ignore[attr-defined]
        if not 0.0 <= fraction <= 1.0:
            problems.append(f"contact_fraction={fraction:g}: must lie in [0, 1] (the share of steps on contact frames)")
        share = float(conf.max_contact_frame_share)  # type: ignore[attr-defined]
        if not 0.0 < share <= 1.0:
            problems.append(f"max_contact_frame_share={share:g}: must lie in (0, 1] (the most steps one contact frame "
                            "may take; 1 leaves contact_fraction uncapped)")
        colour = conf.colour_delta  # type: ignore[attr-defined]
        if colour not in COLOUR_DELTAS:
            problems.append(f"colour_delta={colour}: must be one of {', '.join(COLOUR_DELTAS)} "
                            "(add: c_i + d_c as the paper; scale: c_i exp(d_c))")
        d_max = float(conf.d_max)  # type: ignore[attr-defined]
        if not d_max > 0.0:
            problems.append(f"d_max={d_max:g}: must be positive (metres; the paper uses 0.05)")
        select = selection_config(conf)
        problems += [f"select.{problem}" for problem in select.problems()]
        if select.enabled and int(conf.validation.every) <= 0:  # type: ignore[attr-defined]
            problems.append("select.enabled=true needs validation frames: set stage.dynamic.validation.every > 0 "
                            "(e.g. 50), or select.enabled=false")
        return problems + validation_problems(conf) + refinement_problems(conf)


def selection_config(conf: object) -> SelectionConfig:
    """The core's :class:`SelectionConfig` of a ``stage.dynamic`` section."""
    return SelectionConfig(bool(conf.select.enabled), float(conf.select.margin_db))  # type: ignore[attr-defined]


def check_withheld_by_warmup(cfg) -> None:  # noqa: ANN001 - the run's DictConfig
    """The selection judges step 0, the warm-up's model, on stage two's validation frames: the warm-up must not
    have trained on them. ``ValueError`` naming the keys unless it withheld the same frames."""
    warm, dyn = cfg.stage.warmup.validation, cfg.stage.dynamic.validation
    if int(warm.every) <= 0 or int(warm.frames) != int(dyn.frames):
        raise ValueError(
            f"stage.dynamic.select.enabled=true: the warm-up trained on the frames stage two validates on "
            f"(stage.warmup.validation.every={warm.every}, frames={warm.frames}; stage.dynamic.validation.frames="
            f"{dyn.frames}), so step 0 would be judged on frames it saw; set stage.warmup.validation.every > 0 and "
            f"stage.warmup.validation.frames={dyn.frames} (quality=draft and standard do), or "
            f"stage.dynamic.select.enabled=false")


def model_config(cfg, scene: SceneDecision) -> DynamicModelConfig:  # noqa: ANN001 - the run's DictConfig
    """The architecture from ``quality.*`` and ``stage.dynamic.*``; the hand and interaction MLPs only where
    the scene analysis models the hand and the contact."""
    q, conf = cfg.quality, cfg.stage.dynamic
    return DynamicModelConfig(
        hand_mlp=bool(conf.hand_mlp) and scene.model_hand,
        interaction=bool(conf.interaction) and scene.model_interaction, hand_width=int(q.dynamic_width),
        hand_depth=int(q.dynamic_hand_depth), interaction_width=int(q.dynamic_width),
        interaction_depth=int(q.dynamic_interaction_depth), position_frequencies=int(conf.position_frequencies),
        offset_frequencies=int(conf.offset_frequencies), point_feature_dim=int(conf.point_feature_dim),
        geometry_feature_dim=int(q.geometry_feature_dim), pointnet_centres=tuple(int(c) for c in q.pointnet_centres),
        pointnet_width=float(q.pointnet_width), d_max=float(conf.d_max),
        deform_threshold_m=float(conf.deform_threshold_m), colour_delta=str(conf.colour_delta))


@stage(
    "dynamic",
    inputs=("capture", "frames", "fit", "scene", "pbd", "warmup"),
    config_keys=("quality.dynamic_steps", "quality.dynamic_width", "quality.dynamic_hand_depth",
                 "quality.dynamic_interaction_depth", "quality.geometry_feature_dim", "quality.pointnet_width",
                 "quality.pointnet_centres", "model", "stage.dynamic", "method.representation", "method.pbd",
                 "splatting", "stage.warmup", "fit.source", "stage.keypoints.detector"),  # refines_params
    outputs=("gaussians.parquet", "networks.pt", "model.json", "train_log.parquet", "ply", "curve.parquet",
             "params.parquet"),
    # 10: issue 33's faster step (fused layers, fused Adam; rounding-level changes); 9: refine_params, stage two posed
    # from the warm-up's params.parquet; 8: stage.dynamic.select (the kept step and modules); 7: SSIM filtered by
    # shifted sums instead of conv2d (rounding-level changes); 6: the compiled rasterizer's alpha as a power of two
    # (rounding-level)
    version="10",
    per_method=True,
    config_schema=DynamicConfig,
    # resuming is bit-for-bit: it cannot change the result
    cache_exclude=("stage.dynamic.checkpoint_every", "stage.warmup.checkpoint_every"),
    unused_keys=unused_training_settings,
    sources=model_sources,
)
def dynamic(ctx: StageContext) -> None:
    """Stage two on every train camera and frame: H, I, PointNet++, the point features and the Gaussians
    (the ablations and GaussianAvatars: what of it the method keeps), or SplattingAvatar trained on. With
    ``stage.dynamic.validation.every`` > 0 it withholds ``validation.frames`` train frames, validates on them and
    may stop early (``curve.parquet``; docs/how-to/quality-during-training.md). The train motion is posed with the
    warm-up's ``params.parquet`` and, with ``stage.dynamic.refine_params``, refined further; ``params.parquet`` holds
    it as trained on, which ``evaluate``, ``reenact`` and the PLY export pose the train motion with."""
    conf = ctx.cfg.stage.dynamic
    torch.manual_seed(conf.seed)
    fit_dir, pbd_dir = ctx.input_dir("fit"), ctx.input_dir("pbd")
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), "train", "train")
    posed = posed_sequence(fit_dir, TRAIN_SEQUENCE, ctx.cfg, applied_deformation(ctx.cfg, pbd_dir),
                           method_params(ctx.input_dir("warmup"), fit_dir, TRAIN_SEQUENCE))
    if representation(ctx.cfg) == "embedded":
        _train_embedded(ctx, views, posed.meshes, posed.conditioning(ctx.cfg))
        record_refinement(ctx, load_params(fit_dir, TRAIN_SEQUENCE), posed.params, None)
    else:
        _train_bound(ctx, views, posed)


def _train_embedded(ctx: StageContext, views: ViewSet, meshes: MeshSequence, cond: SequenceConditioning) -> None:
    """SplattingAvatar continued from its warm-up for ``quality.dynamic_steps`` (no density control; walking
    goes on), so it trains as many steps as every other method. ``networks.pt`` holds its canonical mesh."""
    conf, q = ctx.cfg.stage.dynamic, ctx.cfg.quality
    if conf.hand_mlp or conf.interaction or conf.select.enabled:
        raise ValueError("method.representation=embedded (SplattingAvatar) has no hand or interaction MLPs and no "
                         "selection: set stage.dynamic.hand_mlp=false, stage.dynamic.interaction=false and "
                         "stage.dynamic.select.enabled=false (method=splatting_avatar does)")
    canonical = meshes.vertices[0]
    model = load_embedded_gaussians(ctx.input_dir("warmup"), meshes.part_names, canonical, meshes.faces)
    validator = Validator(validation_config(conf.validation), views)
    start = time.perf_counter()
    log = train_splatting(model, views, meshes, splatting_config(ctx.cfg, int(q.dynamic_steps), conf, densify=False),
                          checkpoint_dir=ctx.scratch_dir,
                          progress=lambda s: ctx.progress(s, desc="dynamic", total=len(s)), validator=validator)
    steps = validator.end  # steps run
    write_embedded_gaussians(ctx.out_dir / "gaussians.parquet", model, meshes.part_names)
    buffer = io.BytesIO()
    torch.save({"canonical_vertices": canonical.float(), "faces": meshes.faces}, buffer)
    write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "SplattingAvatar's canonical mesh")
    write_json(ctx.out_dir / "model.json", {"representation": "embedded", "part_names": list(meshes.part_names),
                                            "num_gaussians": model.num_gaussians}, "the embedded model")
    _write_plys(ctx, model, cond, meshes, views.num_frames)
    write_records(ctx.out_dir / "train_log.parquet", SPLATTING_TRAIN_LOG, log)
    record_validation(ctx, validator)
    ctx.metrics.update({"steps": steps, "gaussians": model.num_gaussians,
                        "ms_per_step": 1000 * (time.perf_counter() - start - validator.validation_s) / max(steps, 1),
                        "final_loss": log[-1].loss if log else float("nan"),
                        "walked": sum(r.walked for r in log),
                        "rasterizer": resolve_backend(conf.backend, canonical)})


def _write_plys(ctx: StageContext, model: TrainedModel, cond: SequenceConditioning, meshes: MeshSequence,
                num_frames: int) -> None:
    """World-space 3DGS PLYs of the train frames ``stage.dynamic.ply_frames`` asks for (``ply/train_<frame>.ply``)."""
    (ctx.out_dir / "ply").mkdir()
    with torch.no_grad():
        for frame in sorted({min(max(int(f), 0), num_frames - 1) for f in ctx.cfg.stage.dynamic.ply_frames}):
            write_frame_ply(ctx.out_dir / "ply" / f"train_{frame}.ply",
                            posed_gaussians(model, cond, meshes.vertices[frame], frame))


def _train_bound(ctx: StageContext, views: ViewSet, posed: PosedSequence) -> None:
    """The InteractAvatar model (or what of it the method keeps) on top of the warm-up's bound Gaussians."""
    conf, q = ctx.cfg.stage.dynamic, ctx.cfg.quality
    meshes, cond, params = posed.meshes, posed.conditioning(ctx.cfg), frame_params(ctx.cfg, conf, posed)
    if conf.select.enabled:
        check_withheld_by_warmup(ctx.cfg)
    head, _ = templates(ctx.cfg.model)
    gaussians = load_gaussians(ctx.input_dir("warmup"), meshes.part_names)
    arch = model_config(ctx.cfg, load_scene(ctx.input_dir("scene")))
    frame_dims = {"hand_pose": cond.hand_pose.shape[1], "expression": cond.expression.shape[1]}
    model = DynamicAvatar.from_warmup(gaussians, meshes.vertices[0], meshes.faces, meshes.part_names,
                                      head.num_vertices, frame_dims, arch, seed=conf.seed)
    train_cfg = DynamicTrainConfig(
        steps=int(q.dynamic_steps), lambda_dssim=conf.lambda_dssim, scale_weight=conf.scale_weight,
        position_weight=conf.position_weight, patch_weight=conf.patch_weight, eps_s=conf.eps_s, eps_mu=conf.eps_mu,
        lr_mlp=conf.lr_mlp, lr_point_features=conf.lr_point_features, lr_decay=conf.lr_decay,
        contact_fraction=conf.contact_fraction, max_contact_frame_share=conf.max_contact_frame_share,
        patch_min_size=conf.patch_min_size,
        checkpoint_every=conf.checkpoint_every, log_every=conf.log_every, seed=conf.seed, backend=conf.backend,
        selection=selection_config(conf))
    contact = contact_flags(ctx.input_dir("pbd"), "train", views.num_frames)
    validator = Validator(validation_config(conf.validation), views)
    result = train_dynamic(model, views, meshes, cond, contact, train_cfg, checkpoint_dir=ctx.scratch_dir,
                           progress=lambda steps: ctx.progress(steps, desc="dynamic", total=len(steps)),
                           validator=validator, params=params)
    record_refinement(ctx, load_params(ctx.input_dir("fit"), TRAIN_SEQUENCE), posed.params, params)
    if params is not None:  # the PLYs pose the train motion as refined
        meshes, cond = load_sequence(ctx.input_dir("fit"), TRAIN_SEQUENCE, ctx.cfg,
                                     pbd_dir=applied_deformation(ctx.cfg, ctx.input_dir("pbd")), params=params.arrays())
    write_bound_gaussians(ctx.out_dir / "gaussians.parquet", model.gaussians, meshes.part_names)
    buffer = io.BytesIO()
    torch.save(model.network_state(), buffer)
    write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "the dynamic model's networks")
    selection = result.selection.metrics() if result.selection is not None else {}
    write_json(ctx.out_dir / "model.json", {"architecture": asdict(model.cfg), "part_names": list(meshes.part_names),
                                            "num_face_vertices": head.num_vertices, "frame_dims": frame_dims,
                                            "num_gaussians": model.gaussians.num_gaussians, "selection": selection},
               "the dynamic model")
    _write_plys(ctx, model, cond, meshes, views.num_frames)
    log = result.log
    write_records(ctx.out_dir / "train_log.parquet", DYNAMIC_TRAIN_LOG, log)
    record_validation(ctx, validator)
    steps = max(validator.end, 1)
    ctx.metrics.update({
        "steps": validator.end, "gaussians": model.gaussians.num_gaussians,
        "final_loss": log[-1].loss if log else float("nan"),
        "ms_per_step": 1000 * sum(result.seconds.values()) / steps,
        **{f"{k}_ms_per_step": 1000 * v / steps for k, v in result.seconds.items()},
        "interaction_mlp_evaluations": result.interaction_evaluations,
        "interaction_steps": result.interaction_steps,
        "contact_frames": int(contact.sum()),
        "contact_draw_probability": result.contact_probability,
        "rasterizer": resolve_backend(conf.backend, model.mu_cano),
        **selection,
    })
