"""Representations as plug-ins (issue 37): the registry resolves built-in names and ``package.module:Class``,
refuses anything else up front with the key named, and a representation defined outside the project
(``examples/warmup_only.py``) trains, is evaluated and exported through the stages, which call nothing but the
interface."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from avatar.representations import (
    load_trained,
    representation,
    representation_class,
    training_settings,
)
from avatar.representations.bound.representation import BoundRepresentation
from avatar.representations.embedded.representation import EmbeddedRepresentation
from data_schemas.gaussians_ply import read_gaussians_ply
from data_schemas.metrics import METRICS
from data_schemas.tables import read_table
from examples.warmup_only import WarmupOnly, WarmupOnlyAvatar
from pipeline.cli import run_app
from pipeline.config import ConfigError, validate_config
from pipeline.export_ply import export_frame
from stages import REGISTRY
from tests.conftest import compose_cfg

PLUGIN = "examples.warmup_only:WarmupOnly"


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
    assert training_settings(compose_cfg(base)) == ()
    assert training_settings(compose_cfg([*base, "method=splatting_avatar"])) == ("splatting",)
    assert training_settings(compose_cfg([*base, f"method.representation={PLUGIN}"])) == ()
    assert training_settings(compose_cfg([*base, "method.representation=nosuch"])) == ()  # the check names it


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
