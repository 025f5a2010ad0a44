"""A Gaussian representation defined outside the project: the warm-up's bound Gaussians, posed by the mesh and
never trained in stage two (docs/development/adding-a-method.md). It implements the whole interface of
:class:`avatar.representations.Representation` by reusing the bound representation's warm-up and artifacts, and
``tests/stages/test_representations.py`` runs it through the DAG to ``evaluate`` and the PLY export."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import torch

from avatar.artifacts import TRAIN_SEQUENCE, WorldGaussians, load_params
from avatar.artifacts.motion import PosedSequence
from avatar.artifacts.stage_run import StageRun
from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence
from avatar.representations import CanonicalGaussians, Progress, Representation, write_model_info, write_train_plys
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.representation import BoundRepresentation, load_gaussians, write_bound_gaussians
from avatar.training.frame_params import FrameParams
from avatar.training.settings import record_refinement, record_validation, validation_config
from avatar.training.validation import Validator
from data_schemas.gaussians import TRAIN_LOG
from data_schemas.tables import TableSchema, write_records
from data_schemas.writes import write_bytes


@dataclass
class WarmupOnlyAvatar:
    """The warm-up's bound Gaussians, posed by the mesh and nothing else."""

    gaussians: BoundGaussians
    faces: torch.Tensor

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    @property
    def triangles(self) -> torch.Tensor:
        return self.gaussians.binding

    def on_device(self, device: str, precision: str) -> WarmupOnlyAvatar:
        return WarmupOnlyAvatar(self.gaussians.to(device), self.faces.to(device))  # no networks: fp32 alone

    def pose(self, cond: object, vertices: torch.Tensor, frame: int) -> WorldGaussians:
        means, scales, quats = self.gaussians.world(vertices, self.faces)
        return _Posed(means, scales, quats, self.gaussians.opacities(), self.gaussians.colors())


@dataclass
class _Posed:
    """One frame's world-space Gaussians (the :class:`~avatar.render.gaussians.WorldGaussians` fields)."""

    means: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


class WarmupOnly(Representation):
    """A representation of its own: GaussianAvatars' warm-up, not trained in stage two (its stage two only writes the
    warm-up's Gaussians in the dynamic stage's layout). A method names it with
    ``method.representation=examples.warmup_only:WarmupOnly``."""

    own_settings: ClassVar[tuple[str, ...]] = ()
    refines_tracking: ClassVar[bool] = False
    train_logs: ClassVar[dict[str, tuple[TableSchema, tuple[str, ...]]]] = {
        "warmup": (TRAIN_LOG, ("loss", "l1", "dssim"))
    }
    gaussians = BoundGaussians

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
        return BoundRepresentation(self.cfg).warm_up(
            ctx, model, views, meshes, params, validator, progress, out_dir=out_dir, checkpoint_dir=checkpoint_dir
        )

    def train(
        self, ctx: StageRun, views: ViewSet, posed: PosedSequence, validated: PosedSequence | None = None
    ) -> None:
        meshes = posed.meshes
        gaussians = load_gaussians(ctx.input_dir("warmup"), meshes.part_names)
        write_bound_gaussians(ctx.out_dir / "gaussians.parquet", gaussians, meshes.part_names)
        buffer = io.BytesIO()
        torch.save({"faces": meshes.faces}, buffer)
        write_bytes(ctx.out_dir / "networks.pt", buffer.getvalue(), "the mesh's triangles")
        write_model_info(ctx.out_dir, self, {"part_names": list(meshes.part_names)}, "the warm-up-only model")
        write_train_plys(
            ctx, WarmupOnlyAvatar(gaussians, meshes.faces), posed.conditioning(self.cfg), meshes, views.num_frames
        )
        write_records(ctx.out_dir / "train_log.parquet", TRAIN_LOG, [])
        validator = Validator(validation_config(self.cfg.stage.dynamic.validation, views.num_frames), views)
        record_validation(ctx, validator, views.num_frames)
        record_refinement(ctx, load_params(ctx.input_dir("fit"), TRAIN_SEQUENCE), posed.params, None)
        ctx.metrics.update({"steps": 0, "gaussians": gaussians.num_gaussians, "ms_per_step": 0.0})

    @classmethod
    def load(cls, dynamic_dir: Path, info: dict) -> WarmupOnlyAvatar:
        faces = torch.load(dynamic_dir / "networks.pt", weights_only=True)["faces"]
        return WarmupOnlyAvatar(load_gaussians(dynamic_dir, tuple(info["part_names"])), faces)
