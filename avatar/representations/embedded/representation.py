"""The ``embedded`` representation: SplattingAvatar's Gaussians embedded in the mesh (triangle, barycentric
coordinates, displacement along the normal), trained with its own recipe (``splatting.*``) and walking between
triangles."""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import TRAIN_SEQUENCE, PosedGaussians, WorldGaussians, load_params
from avatar.artifacts.motion import PosedSequence
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
from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded.training import SplattingConfig, train_splatting
from avatar.training.frame_params import FrameParams
from avatar.training.loop import advising, learning_rates
from avatar.training.settings import record_refinement, record_validation, validation_config
from avatar.training.validation import ValidationConfig, Validator
from data_schemas.config_sections import core_config, schema_problems, section_schema
from data_schemas.splatting import EMBEDDED_GAUSSIANS, SPLATTING_TRAIN_LOG
from data_schemas.tables import SchemaError, TableSchema, read_table, write_records, write_table
from data_schemas.writes import write_bytes

#: SplattingConfig's fields that ``splatting`` does not hold: the schedule every method shares.
SHARED_SCHEDULE = (
    "steps",
    "densify_until",
    "opacity_reset_interval",
    "max_gaussians",
    "checkpoint_every",
    "log_every",
    "seed",
    "backend",
)
#: Types of ``splatting``, SplattingAvatar's recipe (values in conf/config.yaml).
SplattingSchema = section_schema("SplattingSchema", SplattingConfig, exclude=SHARED_SCHEDULE)


def splatting_config(cfg: DictConfig, steps: int, schedule: DictConfig, *, densify: bool) -> SplattingConfig:
    """SplattingAvatar's training settings: its recipe (``splatting.*``), the stage's schedule, seed and
    rasterizer (``schedule``: ``stage.warmup`` or ``stage.dynamic``); ``densify=False`` for stage two."""
    warm = cfg.stage.warmup
    return core_config(
        SplattingConfig,
        cfg.splatting,
        steps=steps,
        densify_until=float(warm.densify_until) if densify else 0.0,
        opacity_reset_interval=float(warm.opacity_reset_interval),
        max_gaussians=int(warm.max_gaussians),
        checkpoint_every=int(schedule.checkpoint_every),
        log_every=int(schedule.log_every),
        seed=int(schedule.seed),
        backend=str(schedule.backend),
    )


def write_embedded_gaussians(path: Path, model: EmbeddedGaussians, part_names: tuple[str, ...]) -> None:
    """``gaussians.parquet`` of SplattingAvatar's embedded Gaussians (:data:`EMBEDDED_GAUSSIANS`)."""
    state = model.state_tensors()
    write_table(
        path,
        EMBEDDED_GAUSSIANS,
        {
            **{
                k: host(state[k])
                for k in ("triangle", "barycentric", "displacement", "log_scales", "quats", "opacity_logits", "sh_dc")
            },
            "part": [part_names[i] for i in state["part"].tolist()],
        },
    )


def load_embedded_gaussians(
    stage_dir: Path, part_names: tuple[str, ...], canonical_vertices: torch.Tensor, faces: torch.Tensor
) -> EmbeddedGaussians:
    """The embedded Gaussians of ``gaussians.parquet`` on the canonical mesh (``canonical_vertices`` (V, 3),
    ``faces`` (F, 3))."""
    path = stage_dir / "gaussians.parquet"
    t = read_table(path, EMBEDDED_GAUSSIANS)
    unknown = sorted(set(t["part"]) - set(part_names))
    if unknown:
        raise SchemaError(f"{path}: Gaussians on unknown mesh part(s) {unknown}; expected {part_names}")
    state = {
        k: torch.tensor(np.asarray(t[k]), dtype=torch.float32)
        for k in ("barycentric", "displacement", "log_scales", "quats", "opacity_logits", "sh_dc")
    }
    state["triangle"] = torch.tensor(np.asarray(t["triangle"]))
    state["part"] = torch.tensor([part_names.index(p) for p in t["part"]])
    try:
        return EmbeddedGaussians.from_state_tensors(state, canonical_vertices.float(), faces)
    except ValueError as exc:
        raise SchemaError(f"{path}: {exc}; rerun the stage that wrote it") from exc


@dataclass
class EmbeddedAvatar:
    """A trained SplattingAvatar: its embedded Gaussians on its canonical mesh (no MLPs)."""

    model: EmbeddedGaussians

    @property
    def num_gaussians(self) -> int:
        return self.model.num_gaussians

    @property
    def triangles(self) -> torch.Tensor:
        return self.model.triangle

    def on_device(self, device: str, precision: str) -> EmbeddedAvatar:
        return EmbeddedAvatar(self.model.to(device))  # no networks: nothing runs in another precision

    def pose(self, cond: SequenceConditioning, vertices: torch.Tensor, frame: int) -> WorldGaussians:
        means, scales, quats = self.model.world(vertices, self.model.mesh.faces)
        return PosedGaussians(means, scales, quats, self.model.opacities(), self.model.colors())


class EmbeddedRepresentation(Representation):
    """SplattingAvatar (``method.representation=embedded``): its Gaussians embedded in the mesh, trained with its
    recipe (``splatting.*``) in both stages, with density control in stage one and walking in both; no MLPs, no
    refinement of the tracking."""

    own_settings: ClassVar[tuple[str, ...]] = ("splatting",)
    refines_tracking: ClassVar[bool] = False
    train_logs: ClassVar[dict[str, tuple[TableSchema, tuple[str, ...]]]] = {
        "warmup": (SPLATTING_TRAIN_LOG, ("loss", "l1", "dssim", "mse")),
        "dynamic": (SPLATTING_TRAIN_LOG, ("loss", "l1", "dssim", "mse")),
    }
    gaussians = EmbeddedGaussians

    def problems(self) -> list[str]:
        recipe = schema_problems(self.cfg.get("splatting"), SplattingSchema, "splatting")
        if recipe:
            return recipe
        conf = self.cfg.stage.dynamic
        keys = [
            f"stage.dynamic.{key}"
            for key, on in (
                ("hand_mlp", conf.hand_mlp),
                ("interaction", conf.interaction),
                ("select.enabled", conf.select.enabled),
            )
            if bool(on)
        ]
        problems = [
            f"{key}=true: method.representation={self.key} (SplattingAvatar) has no hand or interaction MLPs "
            f"and no selection; set {key}=false (method=splatting_avatar does)"
            for key in keys
        ]
        return problems + [
            f"stage.{section}.refine_params=true: SplattingAvatar (method.representation={self.key}) "
            f"does not refine the tracking; set it to auto or false"
            for section in ("warmup", "dynamic")
            if str(self.cfg.stage[section].refine_params).lower() == "true"
        ]

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
        assert isinstance(model, EmbeddedGaussians) and params is None
        config = splatting_config(self.cfg, int(self.cfg.quality.warmup_steps), self.cfg.stage.warmup, densify=True)
        with advising("the warm-up", learning_rates("splatting", config)):
            log = train_splatting(
                model, views, meshes, config, checkpoint_dir=checkpoint_dir, progress=progress, validator=validator
            )
        write_embedded_gaussians(out_dir / "gaussians.parquet", model, meshes.part_names)
        write_records(out_dir / "train_log.parquet", SPLATTING_TRAIN_LOG, log)
        return log[-1].loss if log else float("nan")

    def train(
        self, ctx: StageRun, views: ViewSet, posed: PosedSequence, validated: PosedSequence | None = None
    ) -> None:
        """SplattingAvatar continued from its warm-up for ``quality.dynamic_steps`` (no density control; walking
        goes on), so it trains as many steps as every other method. ``networks.pt`` holds its canonical mesh. Its
        :meth:`problems` were refused before any stage ran. With ``validation.retrain`` the validated run (from the
        warm-up's validated run where it kept one; ``validated``: the train motion as that run posed it) only
        measures and may stop early; the model written trains on every frame for the steps it ran."""
        conf, meshes = self.cfg.stage.dynamic, posed.meshes.to(ctx.device)
        canonical = meshes.vertices[0]
        validation = validation_config(conf.validation, views.num_frames)
        warmup_dir = ctx.input_dir("warmup")
        first_dir = warmup_dir / VALIDATED_RUN if validation.enabled and validated is not None else warmup_dir
        retrain = bool(conf.validation.retrain) and validation.enabled
        validator = Validator(validation, views)
        start = time.perf_counter()
        model, log = self._run(ctx, views, meshes, first_dir, validator, "validated" if retrain else "")
        written = validator
        if retrain:
            written = Validator(ValidationConfig(), views, limit=validator.end)
            start = time.perf_counter()
            model, log = self._run(ctx, views, meshes, warmup_dir, written, "final")
        steps = written.end  # steps run
        write_embedded_gaussians(ctx.out_dir / "gaussians.parquet", model, meshes.part_names)
        buffer = io.BytesIO()
        torch.save(host_state({"canonical_vertices": canonical.float(), "faces": meshes.faces}), buffer)
        write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "SplattingAvatar's canonical mesh")
        write_model_info(
            ctx.out_dir,
            self,
            {"part_names": list(meshes.part_names), "num_gaussians": model.num_gaussians},
            "the embedded model",
        )
        write_train_plys(ctx, EmbeddedAvatar(model), posed.conditioning(self.cfg), meshes, views.num_frames)
        write_records(ctx.out_dir / "train_log.parquet", SPLATTING_TRAIN_LOG, log)
        record_validation(ctx, validator, written.train_frames.size)
        seconds = time.perf_counter() - start - written.validation_s
        record_refinement(ctx, load_params(ctx.input_dir("fit"), TRAIN_SEQUENCE), posed.params, None)
        ctx.metrics.update(
            {
                "steps": steps,
                "gaussians": model.num_gaussians,
                "ms_per_step": 1000 * seconds / max(steps, 1),
                "final_loss": log[-1].loss if log else float("nan"),
                "walked": sum(r.walked for r in log),
                "rasterizer": resolve_backend(conf.backend, canonical),
            }
        )

    def _run(
        self, ctx: StageRun, views: ViewSet, meshes: MeshSequence, warmup_dir: Path, validator: Validator, run: str
    ) -> tuple[EmbeddedGaussians, list]:
        """One stage-two run from the warm-up model in ``warmup_dir`` on the frames and for the steps ``validator``
        leaves to it: the model and its loss log. ``run`` names its checkpoint folder."""
        # loaded on the CPU, as the warm-up populated it, then moved to the run's device
        model = load_embedded_gaussians(warmup_dir, meshes.part_names, meshes.vertices[0].cpu(), meshes.faces.cpu()).to(
            meshes.vertices.device
        )
        config = splatting_config(self.cfg, int(self.cfg.quality.dynamic_steps), self.cfg.stage.dynamic, densify=False)
        with advising("stage two", learning_rates("splatting", config)):
            log = train_splatting(
                model,
                views,
                meshes,
                config,
                checkpoint_dir=run_scratch(ctx, run),
                progress=lambda s: ctx.progress(s, desc=f"dynamic ({run})" if run else "dynamic"),
                validator=validator,
            )
        return model, log

    @classmethod
    def load(cls, dynamic_dir: Path, info: dict) -> EmbeddedAvatar:
        state = torch.load(dynamic_dir / "networks.pt", weights_only=True)
        return EmbeddedAvatar(
            load_embedded_gaussians(
                dynamic_dir, tuple(info["part_names"]), state["canonical_vertices"], state["faces"]
            ).requires_grad_(False)
        )
