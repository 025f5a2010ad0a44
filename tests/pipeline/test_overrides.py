"""An override the config has no key or option for is refused in one line naming the key most likely meant, before
any stage runs (exit status 2): Hydra used to end such a command line with its own three-line message and exit 1,
and a ``+key`` added beside the key meant was read by nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.errors import HydraException
from omegaconf import OmegaConf

from data_schemas.key_names import closest_key
from pipeline.config import ConfigError, validate_config
from pipeline.overrides import composition_problem, setting_paths
from stages import REGISTRY
from tests.conftest import compose_cfg, run_cli

KEYS = [
    "subject",
    "run",
    "run.dry",
    "stage",
    "stage.evaluate",
    "stage.evaluate.test_tracking",
    "stage.dynamic.restarts",
]


@pytest.mark.parametrize(
    ("key", "meant"),
    [
        ("evaluate.test_tracking", "stage.evaluate.test_tracking"),  # the key's last components
        ("evaluate.test_trackng", "stage.evaluate.test_tracking"),  # and a typo in them
        ("stage.dynamic.restrats", "stage.dynamic.restarts"),
        ("dry", "run.dry"),
        ("subjet", "subject"),
        ("zzzqqq", None),
    ],
)
def test_the_key_meant_is_found_by_its_last_components_and_its_spelling(key: str, meant: str | None) -> None:
    assert closest_key(key, KEYS) == meant


def _composition_problem(overrides: list[str]) -> str:
    with pytest.raises(HydraException) as caught:
        compose_cfg(overrides)
    return composition_problem(caught.value, overrides, lambda: setting_paths(compose_cfg([])))


@pytest.mark.parametrize(
    ("overrides", "start", "end"),
    [
        (
            ["evaluate.test_tracking=avatar"],
            "evaluate.test_tracking=avatar: no such key",
            "stage.evaluate.test_tracking?",
        ),
        (["quality=draft", "stage.dynamic.restrats=2"], "stage.dynamic.restrats=2: no such key", "dynamic.restarts?"),
        (["tuning_cameras=[cam00]"], "tuning_cameras=[cam00]: no such key", "stage.evaluate.tuning_cameras?"),
        (["zzzqqq=1"], "zzzqqq=1: no such key; docs/reference/config-keys.md lists the keys", "one of your own"),
        (["+seed=1"], "+seed=1: seed is set already", "set it without the + (seed=...)"),
        (["~nosuch"], "~nosuch: no such key to delete", "delete"),
        (
            ["method=interactavtar"],
            "method=interactavtar: no such option of method (gaussian_avatars, ",
            "interactavatar?",
        ),
    ],
)
def test_an_override_hydra_cannot_apply_is_one_line_naming_the_key_meant(
    overrides: list[str], start: str, end: str
) -> None:
    problem = _composition_problem(overrides)
    assert problem.startswith(start) and problem.endswith(end) and "\n" not in problem, problem


def test_the_command_line_is_refused_in_one_line_before_anything_is_written(tmp_path: Path) -> None:
    for args, line in (
        (
            ["evaluate.test_tracking=avatar"],
            "evaluate.test_tracking=avatar: no such key; did you mean stage.evaluate.test_tracking?",
        ),
        (["+evaluate.test_tracking=avatar"], "adds evaluate.test_tracking, which nothing reads; did you mean "),
        (["-m", "subject=synth_a,synth_b", "stage.dynamic.restrats=2"], "did you mean stage.dynamic.restarts?"),
    ):
        done = run_cli(*args, f"paths.outputs={tmp_path / 'out'}", "run.dry=true", timeout=120)
        assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
        assert done.stderr.startswith("interactavatar: error: ") and line in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1, done.stderr
    assert not list((tmp_path / "out").glob("synth_*")), "a subject's folder was written"


def _added(override: str, *extra: str) -> tuple[str, ...]:
    """The problems of the app's config with ``override`` given on the command line (as the CLI records it)."""
    cfg = compose_cfg([*extra, override])
    OmegaConf.update(cfg, "run.overrides", [*extra, override])
    try:
        validate_config(cfg, REGISTRY)
    except ConfigError as exc:
        return exc.problems
    return ()


@pytest.mark.parametrize(
    ("override", "meant"),
    [
        ("+method.representaton=embedded", "method.representation"),
        ("+evaluate.test_tracking=avatar", "stage.evaluate.test_tracking"),
        ("+sed=3", "seed"),
    ],
)
def test_a_key_added_beside_the_key_meant_is_refused(override: str, meant: str) -> None:
    key = override[1:].split("=")[0]
    assert _added(override) == (f"{override}: adds {key}, which nothing reads; did you mean {meant}?",)


def test_a_key_added_with_a_name_of_its_own_is_kept() -> None:
    assert _added("+method.notes=tried a smaller patch weight") == ()
    # a typed section's unknown key is said once, by its schema, with the key meant
    assert _added("+stage.dynamic.restrats=2") == (
        "stage.dynamic.restrats: not a setting of stage.dynamic; did you mean stage.dynamic.restarts?",
    )
