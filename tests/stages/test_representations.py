"""Representations as plug-ins (issue 37): the registry resolves built-in names and ``package.module:Class``,
refuses anything else up front with the key named, and a representation defined only in this test module trains,
is evaluated and exported through the stages, which call nothing but the interface."""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch

from avatar.artifacts import TRAIN_SEQUENCE, WorldGaussians, load_params
from avatar.artifacts.motion import PosedSequence
from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence
from avatar.representations import (
    CanonicalGaussians,
    Progress,
    Representation,
    load_trained,
    representation,
    representation_class,
    unused_training_settings,
    write_model_info,
    write_train_plys,
)
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.representation import BoundRepresentation, load_gaussians, write_bound_gaussians
from avatar.representations.embedded.representation import EmbeddedRepresentation
from avatar.training.frame_params import FrameParams
from avatar.training.settings import record_refinement, record_validation, validation_config
from avatar.training.validation import Validator
from data_schemas.gaussians import TRAIN_LOG
from data_schemas.gaussians_ply import read_gaussians_ply
from data_schemas.metrics import METRICS
from data_schemas.tables import TableSchema, read_table, write_records
from data_schemas.writes import write_bytes
from pipeline.cli import run_app
from pipeline.config import ConfigError, validate_config
from pipeline.export_ply import export_frame
from pipeline.stage import StageContext
from stages import REGISTRY
from tests.conftest import compose_cfg

PLUGIN = f"{__name__}:WarmupOnly"


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

    def pose(self, cond: object, vertices: torch.Tensor, frame: int) -> WorldGaussians:
        means, scales, quats = self.gaussians.world(vertices, self.faces)
        return _Posed(means, scales, quats, self.gaussians.opacities(), self.gaussians.colors())


@dataclass
class _Posed:
    means: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


class WarmupOnly(Representation):
    """A representation of this test's own: GaussianAvatars' warm-up, not trained in stage two (its stage two only
    writes the warm-up's Gaussians in the dynamic stage's layout)."""

    own_settings: ClassVar[tuple[str, ...]] = ()
    refines_tracking: ClassVar[bool] = False
    train_logs: ClassVar[dict[str, tuple[TableSchema, tuple[str, ...]]]] = {
        "warmup": (TRAIN_LOG, ("loss", "l1", "dssim"))
    }
    gaussians = BoundGaussians

    def warm_up(
        self,
        ctx: StageContext,
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
        self, ctx: StageContext, views: ViewSet, posed: PosedSequence, validated: PosedSequence | None = None
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


class NotARepresentation:
    pass


def test_the_registry_resolves_built_in_names_and_module_paths() -> None:
    assert representation_class("bound") is BoundRepresentation
    assert representation_class("embedded") is EmbeddedRepresentation
    assert representation_class(PLUGIN) is WarmupOnly
    for name, expected in (
        ("nosuch", "unknown representation; use one of bound, embedded"),
        ("no.such.module:Thing", "cannot import no.such.module:Thing"),
        (f"{__name__}:Missing", f"cannot import {__name__}:Missing"),
        (f"{__name__}:NotARepresentation", "is not a subclass of"),
    ):
        with pytest.raises(ValueError, match=f"method.representation={name}: .*{expected}"):
            representation_class(name)


def test_the_training_keys_hold_only_the_chosen_representations_settings() -> None:
    base = ["quality=smoke"]
    assert unused_training_settings(compose_cfg(base)) == ("splatting",)
    assert unused_training_settings(compose_cfg([*base, "method=splatting_avatar"])) == ()
    assert unused_training_settings(compose_cfg([*base, f"method.representation={PLUGIN}"])) == ("splatting",)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["method.representation=nosuch"], "method.representation=nosuch: unknown representation"),
        # on the previous code these failed only in stage two, after the warm-up had trained
        (
            ["method=splatting_avatar", "stage.dynamic.hand_mlp=true"],
            "stage.dynamic.hand_mlp=true: method.representation=embedded (SplattingAvatar) has no hand or interaction",
        ),
        (["method=splatting_avatar", "stage.dynamic.select.enabled=true"], "stage.dynamic.select.enabled=true"),
        (
            ["method=splatting_avatar", "stage.warmup.refine_params=true"],
            "stage.warmup.refine_params=true: SplattingAvatar (method.representation=embedded) does not refine",
        ),
    ],
)
def test_what_a_representation_cannot_train_with_is_refused_before_any_stage_runs(overrides, expected) -> None:
    with pytest.raises(ConfigError) as info:
        validate_config(compose_cfg(["quality=smoke", *overrides]), REGISTRY)
    assert expected in str(info.value)


def test_the_built_in_representations_accept_their_methods() -> None:
    for method in (
        "interactavatar",
        "gaussian_avatars",
        "splatting_avatar",
        "no_hand_mlp",
        "no_interaction",
        "no_pbd",
        "no_patch",
    ):
        cfg = compose_cfg(["quality=smoke", f"method={method}"])
        validate_config(cfg, REGISTRY)
        assert representation(cfg).problems() == []


def test_a_representation_defined_in_a_test_trains_is_evaluated_and_exported(tmp_path: Path) -> None:
    """Named by its module path in ``method.representation``: the warm-up trains it, stage two calls its ``train``,
    evaluate and the PLY export load it by what its ``model.json`` records and pose it through its avatar."""
    run_app(
        compose_cfg(
            [
                f"paths.outputs={tmp_path}",
                "quality=smoke",
                "run.progress=false",
                "fit.source=ground_truth",
                "method=gaussian_avatars",
                "method.name=warmup_only",
                f"method.representation={PLUGIN}",
                "run.until=evaluate",
            ]
        )
    )
    method = tmp_path / "synth_a" / "methods" / "warmup_only"
    assert json.loads((method / "dynamic" / "model.json").read_text())["representation"] == PLUGIN
    assert isinstance(load_trained(method / "dynamic"), WarmupOnlyAvatar)
    # stage two changed nothing: its train frame 0 is the warm-up's own PLY of frame 0
    warm, second = (
        read_gaussians_ply(p) for p in (method / "warmup" / "gaussians.ply", method / "dynamic" / "ply" / "train_0.ply")
    )
    np.testing.assert_allclose(second.means, warm.means, atol=1e-6)
    metrics = read_table(method / "evaluate" / "metrics.parquet", METRICS)
    full = np.asarray(metrics["region"]) == "full"
    assert set(metrics["method"]) == {"warmup_only"}
    assert np.isfinite(np.asarray(metrics["psnr"])[full]).all() and np.asarray(metrics["psnr"])[full].mean() > 15
    export_frame(tmp_path / "synth_a", "test", 1, tmp_path / "test_1.ply", method="warmup_only")
    assert len(read_gaussians_ply(tmp_path / "test_1.ply").means) == len(warm.means)
