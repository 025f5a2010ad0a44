"""Stage ``dynamic``: stage two of the paper, the hand MLPs H, the interaction MLPs I and PointNet++ on top
of the warm-up Gaussians (README, "The dynamic model").

Writes ``gaussians.parquet`` (the fine-tuned Gaussians, the warm-up's schema), ``networks.pt`` (a torch
state dict of the MLPs, PointNet++, the point features and the canonical positions; load it with
``torch.load(..., weights_only=True)``), ``model.json`` (the architecture and the conditioning widths:
everything needed to rebuild the model around the two), ``train_log.parquet`` and world-space 3DGS PLYs of
the frames ``stage.dynamic.ply_frames`` asks for (``ply/train_<frame>.ply``).
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass

import numpy as np
import torch

from avatar.dynamic import DynamicAvatar, DynamicModelConfig
from avatar.render.gaussians import resolve_backend
from avatar.training.dynamic import DynamicTrainConfig, train_dynamic
from data_schemas.gaussians import DYNAMIC_TRAIN_LOG
from data_schemas.tables import write_table
from data_schemas.writes import write_bytes, write_json
from pipeline.stage import Resources, StageContext, stage
from stages.common import (
    contact_flags, load_gaussians, load_sequence, load_views, model_sources, templates,
    write_bound_gaussians, write_frame_ply,
)


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

    @classmethod
    def validate(cls, conf: object) -> list[str]:
        """Range problems of a ``stage.dynamic`` section, one line each; empty when it can run."""
        problems = []
        fraction = float(conf.contact_fraction)  # type: ignore[attr-defined]
        if not 0.0 <= fraction <= 1.0:
            problems.append(f"contact_fraction={fraction:g}: must lie in [0, 1] (the share of steps on contact frames)")
        d_max = float(conf.d_max)  # type: ignore[attr-defined]
        if not d_max > 0.0:
            problems.append(f"d_max={d_max:g}: must be positive (metres; the paper uses 0.05)")
        return problems


def model_config(cfg) -> DynamicModelConfig:  # noqa: ANN001 - the run's DictConfig
    """The architecture from ``quality.*`` and ``stage.dynamic.*``."""
    q, conf = cfg.quality, cfg.stage.dynamic
    return DynamicModelConfig(
        hand_mlp=bool(conf.hand_mlp), interaction=bool(conf.interaction), hand_width=int(q.dynamic_width),
        hand_depth=int(q.dynamic_hand_depth), interaction_width=int(q.dynamic_width),
        interaction_depth=int(q.dynamic_interaction_depth), position_frequencies=int(conf.position_frequencies),
        offset_frequencies=int(conf.offset_frequencies), point_feature_dim=int(conf.point_feature_dim),
        geometry_feature_dim=int(q.geometry_feature_dim), pointnet_centres=tuple(int(c) for c in q.pointnet_centres),
        pointnet_width=float(q.pointnet_width), d_max=float(conf.d_max),
        deform_threshold_m=float(conf.deform_threshold_m))


@stage(
    "dynamic",
    inputs=("capture", "frames", "fit", "pbd", "warmup"),
    config_keys=("quality.dynamic_steps", "quality.dynamic_width", "quality.dynamic_hand_depth",
                 "quality.dynamic_interaction_depth", "quality.geometry_feature_dim", "quality.pointnet_width",
                 "quality.pointnet_centres", "model", "stage.dynamic"),
    outputs=("gaussians.parquet", "networks.pt", "model.json", "train_log.parquet", "ply"),
    version="2",
    resources=Resources(cpus=2, gpus=0),
    config_schema=DynamicConfig,
    cache_exclude=("stage.dynamic.checkpoint_every",),  # resuming is bit-for-bit: it cannot change the result
    sources=model_sources,
)
def dynamic(ctx: StageContext) -> None:
    """Train H, I, PointNet++, the point features and the Gaussians on every train camera and frame."""
    conf, q = ctx.cfg.stage.dynamic, ctx.cfg.quality
    torch.manual_seed(conf.seed)
    head, _ = templates(ctx.cfg.model)
    fit_dir, pbd_dir = ctx.input_dir("fit"), ctx.input_dir("pbd")
    views = load_views(ctx.input_dir("capture"), ctx.input_dir("frames"), "train", "train")
    meshes, cond = load_sequence(fit_dir, "train", ctx.cfg, pbd_dir=pbd_dir)
    gaussians = load_gaussians(ctx.input_dir("warmup"), meshes.part_names)
    arch = model_config(ctx.cfg)
    frame_dims = {"hand_pose": cond.hand_pose.shape[1], "expression": cond.expression.shape[1]}
    model = DynamicAvatar.from_warmup(gaussians, meshes.vertices[0], meshes.faces, meshes.part_names,
                                      head.num_vertices, frame_dims, arch, seed=conf.seed)
    train_cfg = DynamicTrainConfig(
        steps=int(q.dynamic_steps), lambda_dssim=conf.lambda_dssim, scale_weight=conf.scale_weight,
        position_weight=conf.position_weight, patch_weight=conf.patch_weight, eps_s=conf.eps_s, eps_mu=conf.eps_mu,
        lr_mlp=conf.lr_mlp, lr_point_features=conf.lr_point_features, lr_decay=conf.lr_decay,
        contact_fraction=conf.contact_fraction, patch_min_size=conf.patch_min_size,
        checkpoint_every=conf.checkpoint_every, log_every=conf.log_every, seed=conf.seed, backend=conf.backend)
    contact = contact_flags(pbd_dir, "train", views.num_frames)
    result = train_dynamic(model, views, meshes, cond, contact, train_cfg, checkpoint_dir=ctx.scratch_dir,
                           progress=lambda steps: ctx.progress(steps, desc="dynamic", total=len(steps)))
    write_bound_gaussians(ctx.out_dir / "gaussians.parquet", model.gaussians, meshes.part_names)
    buffer = io.BytesIO()
    torch.save(model.network_state(), buffer)
    write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "the dynamic model's networks")
    write_json(ctx.out_dir / "model.json", {"architecture": asdict(model.cfg), "part_names": list(meshes.part_names),
                                            "num_face_vertices": head.num_vertices, "frame_dims": frame_dims,
                                            "num_gaussians": model.gaussians.num_gaussians}, "the dynamic model")
    (ctx.out_dir / "ply").mkdir()
    with torch.no_grad():
        for frame in sorted({min(max(int(f), 0), views.num_frames - 1) for f in conf.ply_frames}):
            write_frame_ply(ctx.out_dir / "ply" / f"train_{frame}.ply", model(cond.frame(frame), meshes.vertices[frame]))
    log = result.log
    write_table(ctx.out_dir / "train_log.parquet", DYNAMIC_TRAIN_LOG,
                {name: np.array([getattr(r, name) for r in log]) for name in DYNAMIC_TRAIN_LOG.column_names})
    steps = max(int(q.dynamic_steps), 1)
    ctx.metrics.update({
        "steps": int(q.dynamic_steps), "gaussians": model.gaussians.num_gaussians,
        "final_loss": log[-1].loss if log else float("nan"),
        "ms_per_step": 1000 * sum(result.seconds.values()) / steps,
        **{f"{k}_ms_per_step": 1000 * v / steps for k, v in result.seconds.items()},
        "interaction_mlp_evaluations": result.interaction_evaluations,
        "interaction_steps": result.interaction_steps,
        "contact_frames": int(contact.sum()),
        "rasterizer": resolve_backend(conf.backend, model.mu_cano),
    })
