"""Cache keys hold what a stage's output depends on for this method and solver, and nothing else (issue 37):
a setting the configuration never reads reruns nothing; one it reads reruns the stages that read it."""

from __future__ import annotations

from typing import ClassVar

import pytest

from examples.warmup_only import WarmupOnly
from pipeline.config import ConfigError, key_config, validate_config
from stages import REGISTRY
from tests.conftest import compose_cfg


def changed_stages(base: list[str], change: list[str]) -> set[str]:
    """The stages whose cache key differs between ``base`` and ``base + change`` (upstream digests aside)."""
    before, after = compose_cfg(base), compose_cfg(base + change)
    return {s.name for s in REGISTRY if key_config(before, s) != key_config(after, s)}


@pytest.mark.parametrize(
    ("method", "change"),
    [
        # SplattingAvatar's recipe is not read by the bound representation
        ("interactavatar", ["splatting.lambda_mse=3.0"]),
        ("gaussian_avatars", ["splatting.walk_every=7"]),
        # the default solver (direct) reads none of the sweeps' settings
        ("interactavatar", ["stage.pbd.solver.iterations=17"]),
        ("interactavatar", ["stage.pbd.solver.relaxation=0.5"]),
        ("interactavatar", ["stage.pbd.solver.chebyshev_rho=0.5"]),
        ("interactavatar", ["stage.pbd.solver.detect_every=7"]),
        # validation off (smoke): nothing withheld, nothing selected, one initialisation
        ("interactavatar", ["stage.dynamic.restarts=3"]),
        ("interactavatar", ["stage.dynamic.validation.fraction=0.3"]),
        ("interactavatar", ["stage.dynamic.validation.stop_when_flat.enabled=true"]),
        ("interactavatar", ["stage.dynamic.select.margin_db=0.5"]),
        ("interactavatar", ["stage.warmup.validation.fraction=0.3"]),
        ("splatting_avatar", ["stage.warmup.validation.retrain=false"]),
        # refine_params=auto refines nothing on the ground-truth keypoints' fit; SplattingAvatar never refines
        ("interactavatar", ["stage.warmup.params_lr.pose=0.001"]),
        ("interactavatar", ["stage.dynamic.params_centred=false"]),
        ("splatting_avatar", ["stage.warmup.params_lr.expression=0.1"]),
        # the held-out motion posed as the tracker tracked it: the avatar's tracking is not run
        ("interactavatar", ["stage.evaluate.tuning_cameras=[cam00]"]),
        ("interactavatar", ["stage.evaluate.tracking.steps=3"]),
    ],
)
def test_a_setting_the_configuration_never_reads_reruns_nothing(method: str, change: list[str]) -> None:
    assert changed_stages([f"method={method}"], change) == set()


@pytest.mark.parametrize(
    ("base", "change", "expected"),
    [
        # draft validates and selects: the restarts and the withheld share are read
        (["quality=draft"], ["stage.dynamic.restarts=3"], {"dynamic"}),
        (["quality=draft"], ["stage.dynamic.validation.fraction=0.3"], {"dynamic"}),
        (["quality=draft"], ["stage.warmup.validation.fraction=0.3"], {"warmup", "dynamic"}),
        # validation without the selection: one initialisation, whatever restarts says
        (["quality=draft", "stage.dynamic.select.enabled=false"], ["stage.dynamic.restarts=3"], set()),
        (["stage.warmup.refine_params=true"], ["stage.warmup.params_lr.pose=0.001"], {"warmup", "dynamic"}),
        (["stage.keypoints.detector=mediapipe"], ["stage.warmup.params_lr.pose=0.001"], {"warmup", "dynamic"}),
        (["stage.keypoints.detector=mediapipe"], ["stage.dynamic.params_centred=false"], {"dynamic"}),
        (["stage.evaluate.test_tracking=avatar"], ["stage.evaluate.tuning_cameras=[cam00]"], {"evaluate"}),
        (["stage.evaluate.test_tracking=avatar"], ["stage.evaluate.tracking.steps=3"], {"evaluate"}),
    ],
)
def test_settings_a_configuration_reads_only_when_switched_on_rerun_it_then(
    base: list[str], change: list[str], expected: set[str]
) -> None:
    assert changed_stages(base, change) == expected


@pytest.mark.parametrize(
    ("base", "change", "expected"),
    [
        (["method=splatting_avatar"], ["splatting.lambda_mse=3.0"], {"warmup", "dynamic"}),
        (["method=interactavatar"], ["stage.pbd.solver.direct_outer=3"], {"pbd", "evaluate", "reenact"}),
        # a method without PBD drives its avatar without the solver: only the shared pbd stage reruns
        (["method=gaussian_avatars"], ["stage.pbd.solver.direct_outer=3"], {"pbd"}),
        (
            ["method=interactavatar", "stage.pbd.solver.method=jacobi"],
            ["stage.pbd.solver.iterations=17"],
            {"pbd", "evaluate", "reenact"},
        ),
        (["method=interactavatar", "stage.pbd.solver.method=jacobi"], ["stage.pbd.solver.direct_outer=3"], set()),
    ],
)
def test_a_setting_the_configuration_reads_reruns_the_stages_that_read_it(
    base: list[str], change: list[str], expected: set[str]
) -> None:
    assert changed_stages(base, change) == expected


class OwnRecipe(WarmupOnly):
    """A plug-in representation with a config section of its own, as SplattingAvatar's ``splatting``."""

    own_settings: ClassVar[tuple[str, ...]] = ("own_recipe",)


OWN_RECIPE = ["method=gaussian_avatars", f"method.representation={__name__}:OwnRecipe", "+own_recipe.strength=1"]


def test_a_plugin_representations_own_settings_rerun_its_training_stages() -> None:
    """Only the built-in representations' sections used to enter the keys: a plug-in's own setting reran nothing."""
    assert changed_stages(OWN_RECIPE, ["own_recipe.strength=2"]) == {"warmup", "dynamic"}
    # and the built-in recipe it never reads reruns nothing
    assert changed_stages(OWN_RECIPE, ["splatting.lambda_mse=3.0"]) == set()


def test_a_plugin_representations_own_section_must_be_set() -> None:
    with pytest.raises(ConfigError, match="stage 'warmup' depends on config key 'own_recipe', which is not set"):
        validate_config(compose_cfg(OWN_RECIPE[:-1]), REGISTRY)


def test_an_unused_key_must_be_one_of_the_stage_keys() -> None:
    from dataclasses import replace

    stage = replace(REGISTRY["warmup"], unused_keys=lambda cfg: ("stage.pbd.solver",))
    with pytest.raises(ValueError, match="unused key 'stage.pbd.solver' is not one of its config_keys"):
        key_config(compose_cfg([]), stage)


@pytest.mark.parametrize(
    ("method", "expected"),
    [
        # only contact simulation reads the stiffness: the fit, the scene and the training keep their keys
        ("interactavatar", {"pbd", "evaluate", "reenact"}),
        # a method without PBD drives its avatar without it: only the shared pbd stage reruns
        ("gaussian_avatars", {"pbd"}),
    ],
)
def test_the_face_stiffness_reruns_only_the_stages_that_simulate_contact(
    tmp_path, method: str, expected: set[str]
) -> None:
    """A model.* setting enters the keys of the stages that read it, not of every stage that poses a template:
    a stiffness file used to recompute the fit (minutes, same bytes) before pbd read it."""
    stiffness = tmp_path / "thickness.npy"
    stiffness.write_bytes(b"")
    assert changed_stages([f"method={method}"], [f"model.face_stiffness_path={stiffness}"]) == expected


def test_a_template_file_reruns_every_stage_that_poses_the_templates(tmp_path) -> None:
    flame = tmp_path / "generic_model.pkl"
    flame.write_bytes(b"")
    posing = {"fit", "scene", "pbd", "warmup", "dynamic", "evaluate", "reenact", "viewer", "report"}
    assert changed_stages(["method=interactavatar"], [f"model.flame_path={flame}"]) == posing
