"""The ``bound`` representation: Gaussians bound to the FLAME and MANO triangles (GaussianAvatars), with, in stage
two, the hand MLPs H, the interaction MLPs I and PointNet++ of InteractAvatar (what of them the method keeps)."""

from __future__ import annotations

import io
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import TRAIN_SEQUENCE, WorldGaussians, contact_flags, load_params, load_scene
from avatar.artifacts.motion import PosedSequence, posed_with_offsets, templates
from avatar.artifacts.stage_run import StageRun
from avatar.device import host, host_state
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence
from avatar.render.gaussians import resolve_backend
from avatar.representations import (
    VALIDATED_RUN,
    CanonicalGaussians,
    Progress,
    Representation,
    run_scratch,
    write_model_info,
    write_train_plys,
)
from avatar.representations.bound.dynamic_model import DynamicAvatar, DynamicModelConfig
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.stage_two import DynamicTrainConfig, DynamicTrainResult, train_dynamic
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.scene import SceneDecision
from avatar.training.avatar_tracking import PoseFrame
from avatar.training.frame_params import FrameParams
from avatar.training.loop import advising, learning_rates
from avatar.training.selection import SelectionConfig
from avatar.training.settings import (
    frame_params,
    param_learning_rates,
    record_refinement,
    record_validation,
    validation_config,
)
from avatar.training.validation import ValidationConfig, Validator
from data_schemas.config_sections import core_config
from data_schemas.gaussians import BOUND_GAUSSIANS, DYNAMIC_TRAIN_LOG, TRAIN_LOG
from data_schemas.tables import SchemaError, TableSchema, read_table, write_records, write_table
from data_schemas.writes import write_bytes


def load_gaussians(warmup_dir: Path, part_names: tuple[str, ...]) -> BoundGaussians:
    """The trained model from ``gaussians.parquet`` (parts mapped to indices of ``part_names``)."""
    path = warmup_dir / "gaussians.parquet"
    t = read_table(path, BOUND_GAUSSIANS)
    unknown = sorted(set(t["part"]) - set(part_names))
    if unknown:
        raise SchemaError(f"{path}: Gaussians bound to unknown mesh part(s) {unknown}; expected {part_names}")
    as_tensor = lambda name: torch.tensor(np.asarray(t[name]), dtype=torch.float32)  # noqa: E731
    return BoundGaussians(
        local_means=as_tensor("local_means"),
        log_scales=as_tensor("log_scales"),
        quats=as_tensor("quats"),
        opacity_logits=as_tensor("opacity_logits"),
        sh_dc=as_tensor("sh_dc"),
        binding=torch.tensor(np.array(t["binding"])),
        part=torch.tensor([part_names.index(p) for p in t["part"]]),
    )


def write_bound_gaussians(path: Path, model: BoundGaussians, part_names: tuple[str, ...]) -> None:
    """``gaussians.parquet`` of ``model`` (the inverse of :func:`load_gaussians`)."""
    with torch.no_grad():
        write_table(
            path,
            BOUND_GAUSSIANS,
            {
                "binding": host(model.binding),
                "part": [part_names[i] for i in model.part.tolist()],
                "local_means": host(model.local_means),
                "log_scales": host(model.log_scales),
                "quats": host(model.quats),
                "opacity_logits": host(model.opacity_logits),
                "sh_dc": host(model.sh_dc),
            },
        )


def architecture_record(cfg: DynamicModelConfig) -> dict[str, Any]:
    """``model.json``'s ``architecture``: the model's config, without ``heads`` where it is the paper's
    ``per_parameter`` (so that file reads as it did before the setting existed; loading defaults to it)."""
    record = asdict(cfg)
    if record["heads"] == "per_parameter":
        del record["heads"]
    return record


def load_dynamic(dynamic_dir: Path) -> DynamicAvatar:
    """The dynamic stage's trained model (``model.json``, ``gaussians.parquet``, ``networks.pt``)."""
    info = json.loads((dynamic_dir / "model.json").read_text())
    part_names = tuple(info["part_names"])
    gaussians = load_gaussians(dynamic_dir, part_names)
    arch = info["architecture"]
    settings: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in arch.items()}
    cfg = DynamicModelConfig(**settings)
    state = torch.load(dynamic_dir / "networks.pt", weights_only=True)
    model = DynamicAvatar(
        gaussians, state["mu_cano"], state["faces"], part_names, int(info["num_face_vertices"]), info["frame_dims"], cfg
    )
    trained = "shared" if any(".trunk." in key for key in state) else "per_parameter"
    if any(key.startswith(("hand_geo.", "hand_app.", "interaction.")) for key in state) and trained != cfg.heads:
        raise SchemaError(
            f"{dynamic_dir / 'networks.pt'}: holds heads={trained} networks, but model.json says heads={cfg.heads}; "
            "the two files come from different runs: rerun the dynamic stage"
        )
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("gaussians.")]
    if missing or unexpected:
        raise SchemaError(
            f"{dynamic_dir / 'networks.pt'}: does not match model.json (missing {missing[:3]}, "
            f"unexpected {unexpected[:3]}); rerun the dynamic stage"
        )
    return model


def selection_config(conf: DictConfig) -> SelectionConfig:
    """The core's :class:`SelectionConfig` of a ``stage.dynamic`` section."""
    return SelectionConfig(bool(conf.select.enabled), float(conf.select.margin_db))


def withheld_problems(cfg: DictConfig) -> list[str]:
    """The selection judges step 0, the warm-up's model, on stage two's validation frames: the warm-up must not have
    trained on them. One line naming the keys unless it withheld the same frames (validation on, the same fraction and
    floor), empty otherwise or without the selection."""
    warm, dyn = cfg.stage.warmup.validation, cfg.stage.dynamic.validation
    if not bool(cfg.stage.dynamic.select.enabled) or int(dyn.every) <= 0:
        return []
    same = all(float(warm[key]) == float(dyn[key]) for key in ("fraction", "min_train_frames"))
    if int(warm.every) > 0 and same:
        return []
    return [
        f"stage.dynamic.select.enabled=true: the warm-up trained on the frames stage two validates on "
        f"(stage.warmup.validation.every={warm.every}, fraction={warm.fraction}, min_train_frames="
        f"{warm.min_train_frames}; stage.dynamic.validation.fraction={dyn.fraction}, min_train_frames="
        f"{dyn.min_train_frames}), so step 0 would be judged on frames it saw; set stage.warmup.validation.every > 0 "
        f"and its fraction and min_train_frames to stage two's (quality=draft, standard and paper do), or "
        f"stage.dynamic.select.enabled=false"
    ]


#: DynamicModelConfig's fields that the quality preset sets (``quality.dynamic_*``, ``quality.pointnet_*``,
#: ``quality.geometry_feature_dim``), not ``stage.dynamic``.
PRESET_ARCHITECTURE = (
    "hand_width",
    "hand_depth",
    "interaction_width",
    "interaction_depth",
    "geometry_feature_dim",
    "pointnet_centres",
    "pointnet_width",
)


def model_config(cfg: DictConfig, scene: SceneDecision) -> DynamicModelConfig:
    """The architecture from ``quality.*`` and ``stage.dynamic.*``; the hand and interaction MLPs only where
    the scene analysis models the hand and the contact."""
    q, conf = cfg.quality, cfg.stage.dynamic
    return core_config(
        DynamicModelConfig,
        conf,
        hand_mlp=bool(conf.hand_mlp) and scene.model_hand,
        interaction=bool(conf.interaction) and scene.model_interaction,
        hand_width=int(q.dynamic_width),
        hand_depth=int(q.dynamic_hand_depth),
        interaction_width=int(q.dynamic_width),
        interaction_depth=int(q.dynamic_interaction_depth),
        geometry_feature_dim=int(q.geometry_feature_dim),
        pointnet_centres=tuple(int(c) for c in q.pointnet_centres),
        pointnet_width=float(q.pointnet_width),
    )


def warmup_train_config(cfg: DictConfig) -> WarmupTrainConfig:
    """The warm-up's :class:`WarmupTrainConfig` of ``stage.warmup`` and ``quality.warmup_steps``."""
    return core_config(WarmupTrainConfig, cfg.stage.warmup, steps=int(cfg.quality.warmup_steps))


def dynamic_train_config(cfg: DictConfig) -> DynamicTrainConfig:
    """Stage two's :class:`DynamicTrainConfig` of ``stage.dynamic`` and ``quality.dynamic_steps``."""
    return core_config(
        DynamicTrainConfig,
        cfg.stage.dynamic,
        steps=int(cfg.quality.dynamic_steps),
        selection=selection_config(cfg.stage.dynamic),
    )


def stage_learning_rates(
    cfg: DictConfig, stage: str, config: WarmupTrainConfig | DynamicTrainConfig, refining: bool
) -> dict[str, float]:
    """The learning rates of training stage ``stage`` (``warmup``, ``dynamic``), config key -> value: its recipe's
    (``config``, built from ``stage.<stage>``; not stage two's ``lr_decay``, a ratio) and, where it refines the train
    motion's parameters, its ``params_lr``."""
    rates = learning_rates(f"stage.{stage}", config, exclude=("lr_decay",))
    if refining:
        rates |= learning_rates(f"stage.{stage}.params_lr", param_learning_rates(cfg.stage[stage]), start="")
    return rates


def restart_seed(seed: int, restart: int) -> int:
    """The seed of stage two's ``restart``-th initialisation (``stage.dynamic.restarts``): the run's own seed for the
    first, so that one restart is the run without restarts."""
    return seed + 1000 * restart


@dataclass
class StageTwoRun:
    """One training run of stage two: the train motion it was posed with, the model and refined parameters it left, its
    validator (the frames it withheld, its curve), the loop's result (what it selected), its seed and the conditioning
    widths the model was built for."""

    posed: PosedSequence
    model: DynamicAvatar
    params: FrameParams | None
    validator: Validator
    result: DynamicTrainResult
    seed: int
    frame_dims: dict[str, int]

    @property
    def selection_psnr(self) -> float:
        """The validation PSNR (dB) of what the selection kept; NaN where it did not run."""
        return self.result.selection.psnr if self.result.selection is not None else float("nan")


@dataclass
class BoundAvatar:
    """A trained bound model (:class:`DynamicAvatar`: the Gaussians and what of H, I and PointNet++ it keeps)."""

    model: DynamicAvatar

    @property
    def num_gaussians(self) -> int:
        return self.model.gaussians.num_gaussians

    @property
    def triangles(self) -> torch.Tensor:
        return self.model.gaussians.binding

    def on_device(self, device: str, precision: str) -> BoundAvatar:
        model = self.model.to(device)
        model.precision = precision
        return BoundAvatar(model)

    def pose(self, cond: SequenceConditioning, vertices: torch.Tensor, frame: int) -> WorldGaussians:
        return self.model(cond.frame(frame), vertices)

    def frame_pose(self) -> PoseFrame:
        """:func:`~avatar.representations.frame_pose`: the networks' products of the position code and the point
        features (:meth:`DynamicAvatar.fixed_inputs`) computed now, once, and handed to every frame."""
        fixed = self.model.fixed_inputs()
        return lambda cond, vertices: self.model(cond, vertices, None, fixed)


class BoundRepresentation(Representation):
    """GaussianAvatars' binding (``method.representation=bound``): stage one trains static Gaussians bound to the
    triangles (:func:`~avatar.representations.bound.warmup.train_warmup`); stage two adds InteractAvatar's MLPs
    and PointNet++ (:func:`~avatar.representations.bound.stage_two.train_dynamic`), as far as ``stage.dynamic`` and
    the scene analysis keep them."""

    train_logs: ClassVar[dict[str, tuple[TableSchema, tuple[str, ...]]]] = {
        "warmup": (TRAIN_LOG, ("loss", "l1", "dssim")),
        "dynamic": (DYNAMIC_TRAIN_LOG, ("loss", "l1", "dssim", "patch")),
    }
    gaussians = BoundGaussians

    def problems(self) -> list[str]:
        return withheld_problems(self.cfg)

    def warm_up(
        self,
        ctx: StageRun,
        model: CanonicalGaussians,
        views: ViewSet,
        meshes: MeshSequence,
        params: FrameParams | None,
        validator: Validator,
        progress: Progress,
        *,
        out_dir: Path,
        checkpoint_dir: Path | None,
    ) -> float:
        assert isinstance(model, BoundGaussians)
        config = warmup_train_config(self.cfg)
        with advising("the warm-up", stage_learning_rates(self.cfg, "warmup", config, params is not None)):
            log = train_warmup(
                model,
                views,
                meshes,
                config,
                checkpoint_dir=checkpoint_dir,
                progress=progress,
                validator=validator,
                params=params,
            )
        write_bound_gaussians(out_dir / "gaussians.parquet", model, meshes.part_names)
        write_records(out_dir / "train_log.parquet", TRAIN_LOG, log)
        return log[-1].loss if log else float("nan")

    def train(
        self, ctx: StageRun, views: ViewSet, posed: PosedSequence, validated: PosedSequence | None = None
    ) -> None:
        """Stage two. With validation on, the validated run(s) (``stage.dynamic.restarts`` of them, from the warm-up's
        validated run where it kept one) choose the step and the modules (:mod:`avatar.training.selection`); with
        ``validation.retrain`` the model written then trains on every train frame, from the warm-up's final model,
        for exactly the chosen steps and with only the chosen modules (docs/explanation/selection.md)."""
        conf = self.cfg.stage.dynamic
        validation = validation_config(conf.validation, views.num_frames)
        select = bool(conf.select.enabled) and validation.enabled  # nothing withheld: nothing to choose on
        if select and (problems := withheld_problems(self.cfg)):
            raise ValueError(problems[0])
        retrain = bool(conf.validation.retrain) and validation.enabled
        # the validated run(s) start from the warm-up's validated run where it kept one (it withheld the same frames)
        warmup_dir = ctx.input_dir("warmup")
        first_dir = warmup_dir / VALIDATED_RUN if validation.enabled and validated is not None else warmup_dir
        first_posed = validated if validation.enabled and validated is not None else posed
        arch = model_config(self.cfg, load_scene(ctx.input_dir("scene")))
        contact = contact_flags(ctx.input_dir("pbd"), TRAIN_SEQUENCE, views.num_frames)
        restarts = int(conf.restarts) if select else 1
        runs = [
            self._run(
                ctx,
                views,
                first_posed,
                first_dir,
                arch,
                contact,
                Validator(validation, views),
                seed=restart_seed(int(conf.seed), i),
                select=select,
                run=(f"restart{i}" if restarts > 1 else "validated") if retrain or restarts > 1 else "",
            )
            for i in range(restarts)
        ]
        chosen = max(runs, key=lambda r: r.selection_psnr) if select else runs[0]  # ties: the first
        written = chosen
        if retrain:
            selection = chosen.result.selection
            steps = selection.selected_step if selection is not None else chosen.validator.end
            kept = selection.kept if selection is not None else {"hand_mlp": True, "interaction": True}
            final_arch = replace(
                arch, hand_mlp=arch.hand_mlp and kept["hand_mlp"], interaction=arch.interaction and kept["interaction"]
            )
            written = self._run(
                ctx,
                views,
                posed,
                warmup_dir,
                final_arch,
                contact,
                Validator(ValidationConfig(), views, limit=steps),
                seed=chosen.seed,
                select=False,
                run="final",
            )
        self._write(ctx, views, written, chosen, runs, retrain, contact)

    def _run(
        self,
        ctx: StageRun,
        views: ViewSet,
        posed: PosedSequence,
        warmup_dir: Path,
        arch: DynamicModelConfig,
        contact: np.ndarray,
        validator: Validator,
        *,
        seed: int,
        select: bool,
        run: str,
    ) -> StageTwoRun:
        """One stage-two run from the warm-up model in ``warmup_dir`` on the frames ``validator`` leaves to training,
        posed with ``posed`` (the parameters that warm-up trained on), drawing the ``contact`` (T,) frames first;
        ``run`` names its checkpoint folder."""
        conf = self.cfg.stage.dynamic
        meshes, cond, params = (
            posed.meshes.to(ctx.device),
            posed.conditioning(self.cfg).to(ctx.device),
            frame_params(self.cfg, conf, posed, self.refines_tracking, ctx.device),
        )
        head, _ = templates(self.cfg.model)
        frame_dims = {"hand_pose": cond.hand_pose.shape[1], "expression": cond.expression.shape[1]}
        # built on the CPU, where the seed initialises the networks alike on every machine, then moved
        model = DynamicAvatar.from_warmup(
            load_gaussians(warmup_dir, meshes.part_names),
            posed.meshes.vertices[0],
            posed.meshes.faces,
            meshes.part_names,
            head.num_vertices,
            frame_dims,
            arch,
            seed=seed,
        ).to(ctx.device)
        model.precision = ctx.precision
        train_cfg = dynamic_train_config(self.cfg)
        train_cfg = replace(train_cfg, seed=seed, selection=replace(train_cfg.selection, enabled=select))
        with advising("stage two", stage_learning_rates(self.cfg, "dynamic", train_cfg, params is not None)):
            result = train_dynamic(
                model,
                views,
                meshes,
                cond,
                contact,
                train_cfg,
                checkpoint_dir=run_scratch(ctx, run),
                progress=lambda steps: ctx.progress(steps, desc=f"dynamic ({run})" if run else "dynamic"),
                validator=validator,
                params=params,
            )
        return StageTwoRun(posed, model, params, validator, result, seed, frame_dims)

    def _write(
        self,
        ctx: StageRun,
        views: ViewSet,
        written: StageTwoRun,
        chosen: StageTwoRun,
        runs: list[StageTwoRun],
        retrain: bool,
        contact: np.ndarray,
    ) -> None:
        """The stage's outputs and metrics: the model of ``written``, what ``chosen`` (the best of ``runs``) chose."""
        conf, model, params, result, posed = (
            self.cfg.stage.dynamic,
            written.model,
            written.params,
            written.result,
            written.posed,
        )
        head, _ = templates(self.cfg.model)
        fit_dir = ctx.input_dir("fit")
        record_refinement(ctx, load_params(fit_dir, TRAIN_SEQUENCE), posed.params, params)
        if params is not None:  # the PLYs pose the train motion as refined, with the contact offsets read before
            posed = posed_with_offsets(params.arrays(), self.cfg, posed.offsets)
        meshes, cond = posed.meshes.to(ctx.device), posed.conditioning(self.cfg).to(ctx.device)
        write_bound_gaussians(ctx.out_dir / "gaussians.parquet", model.gaussians, meshes.part_names)
        buffer = io.BytesIO()
        torch.save(host_state(model.network_state()), buffer)
        write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "the dynamic model's networks")
        selection = chosen.result.selection.metrics() if chosen.result.selection is not None else {}
        if len(runs) > 1:
            selection |= {
                "restarts": len(runs),
                "selected_restart": runs.index(chosen),
                "selected_seed": chosen.seed,
                **{f"restart{i}_selection_psnr": r.selection_psnr for i, r in enumerate(runs)},
            }
        write_model_info(
            ctx.out_dir,
            self,
            {
                "architecture": architecture_record(model.cfg),
                "part_names": list(meshes.part_names),
                "num_face_vertices": head.num_vertices,
                "frame_dims": written.frame_dims,
                "num_gaussians": model.gaussians.num_gaussians,
                "selection": selection,
                "retrained_on_all_frames": retrain,
            },
            "the dynamic model",
        )
        write_train_plys(ctx, BoundAvatar(model), cond, meshes, views.num_frames)
        log = result.log
        write_records(ctx.out_dir / "train_log.parquet", DYNAMIC_TRAIN_LOG, log)
        record_validation(ctx, chosen.validator, written.validator.train_frames.size)
        steps = max(written.validator.end, 1)
        ctx.metrics.update(
            {
                "steps": written.validator.end,
                "gaussians": model.gaussians.num_gaussians,
                "final_loss": log[-1].loss if log else float("nan"),
                "ms_per_step": 1000 * sum(result.seconds.values()) / steps,
                **{f"{k}_ms_per_step": 1000 * v / steps for k, v in result.seconds.items()},
                "interaction_mlp_evaluations": result.interaction_evaluations,
                "interaction_steps": result.interaction_steps,
                "contact_frames": int(contact.sum()),
                "contact_draw_probability": result.contact_probability,
                "retrained_on_all_frames": retrain,
                "rasterizer": resolve_backend(conf.backend, model.mu_cano),
                "heads": model.cfg.heads,
                **selection,
            }
        )

    @classmethod
    def load(cls, dynamic_dir: Path, info: dict) -> BoundAvatar:
        return BoundAvatar(load_dynamic(dynamic_dir).requires_grad_(False))
