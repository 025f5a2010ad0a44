"""One definition per setting (issue 37): the config sections that feed a training loop or the dynamic model are
typed by its own config dataclass and set every one of its settings, and their YAML defaults and descriptions are
generated from the dataclass (avatar.config_defaults), except the pipeline's own choices."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest
from omegaconf import OmegaConf

from avatar.config_defaults import BLOCKS, CONF_DIR, PIPELINE_CHOICES, rendered
from avatar.fitting.fit import FitConfig
from avatar.fitting.refine import RefineConfig
from avatar.pbd import PBDConfig
from avatar.representations.bound.dynamic_model import DynamicModelConfig
from avatar.representations.bound.representation import (
    PRESET_ARCHITECTURE,
    dynamic_train_config,
    model_config,
    warmup_train_config,
)
from avatar.representations.bound.stage_two import DynamicTrainConfig
from avatar.representations.bound.warmup import WarmupTrainConfig
from avatar.representations.embedded.representation import SHARED_SCHEDULE, SplattingSchema, splatting_config
from avatar.representations.embedded.training import SplattingConfig
from avatar.scene import SceneDecision
from avatar.training.avatar_tracking import AvatarTrackingConfig
from avatar.training.frame_params import ParamLearningRates
from avatar.viewer.codec import CodecConfig
from data_schemas.config_sections import core_config, core_fields, section_schema, yaml_defaults, yaml_value
from pipeline.config import ConfigError, validate_config
from stages import REGISTRY
from stages.dynamic import DynamicConfig
from stages.fit import FitStageConfig
from stages.viewer import ViewerConfig
from stages.warmup import WarmupConfig
from tests.conftest import compose_cfg

#: (core dataclass, its config section, its fields the section does not hold, the section's schema)
SECTIONS = [
    (WarmupTrainConfig, "stage.warmup", ("steps",), WarmupConfig),
    (DynamicTrainConfig, "stage.dynamic", ("steps", "selection"), DynamicConfig),
    (DynamicModelConfig, "stage.dynamic", PRESET_ARCHITECTURE, DynamicConfig),
    (SplattingConfig, "splatting", SHARED_SCHEDULE, SplattingSchema),
    (FitConfig, "stage.fit", ("face_shape_columns",), FitStageConfig),
    (RefineConfig, "stage.fit.refinement", (), RefineConfig),
    (PBDConfig, "stage.pbd.solver", (), PBDConfig),
    (CodecConfig, "stage.viewer", (), ViewerConfig),
    (AvatarTrackingConfig, "stage.evaluate.tracking", (), AvatarTrackingConfig),
    (ParamLearningRates, "stage.warmup.params_lr", (), ParamLearningRates),
]


@pytest.mark.parametrize(
    ("core", "key", "exclude", "schema"), SECTIONS, ids=[f"{s[1]}-{s[0].__name__}" for s in SECTIONS]
)
def test_each_section_types_and_sets_every_hyperparameter_of_its_dataclass(core, key, exclude, schema) -> None:
    section = OmegaConf.select(compose_cfg([]), key)
    typed = {f.name for f in dataclasses.fields(schema)}
    for name, _ in core_fields(core, exclude):
        assert name in section, f"{key}.{name}: a hyperparameter of {core.__name__} that the config cannot set"
        assert name in typed, f"{schema.__name__} does not type {name}"


def test_the_yaml_defaults_are_generated_from_the_dataclasses() -> None:
    """One default and one description per setting: conf/'s blocks are what the dataclasses generate, and every
    block is declared (the settings outside the blocks are the stages' own or the pipeline's choices)."""
    stale = [str(path) for path, text in rendered().items() if path.read_text() != text]
    assert not stale, f"{stale}: run python -m avatar.config_defaults"
    excluded = {core: set(exclude) | set(PIPELINE_CHOICES) for core, _, exclude, _ in SECTIONS}
    assert {b.core for b in BLOCKS} == set(excluded)
    for block in BLOCKS:  # a block leaves out only what its section does not hold and the pipeline's choices
        assert set(block.exclude) <= excluded[block.core], block
    warm = OmegaConf.load(CONF_DIR / "stage" / "warmup.yaml")
    assert warm.checkpoint_every != WarmupTrainConfig(steps=1).checkpoint_every  # a pipeline's choice, by hand


def test_a_setting_without_documentation_is_refused() -> None:
    @dataclass(frozen=True)
    class Undocumented:
        rate: float = 0.1

    with pytest.raises(ValueError, match="Undocumented.rate has no comment: document it in the dataclass"):
        yaml_defaults(Undocumented)
    assert yaml_defaults(_Core, ("steps",)) == ["rate: 0.1  # per step", "name: x  # what it is called"]
    assert yaml_value(5e-05) == "5.0e-05" and yaml_value((0.2, 4)) == "[0.2, 4]" and yaml_value(True) == "true"


def test_the_loops_configs_are_built_from_their_sections_whole() -> None:
    cfg = validate_config(
        compose_cfg(
            [
                "quality=draft",
                "stage.warmup.lr_scale=0.02",
                "stage.dynamic.lr_color=0.01",
                "splatting.max_hops=8",
                "stage.warmup.grad_threshold=0.0003",
            ]
        ),
        REGISTRY,
    )
    static, dynamic = warmup_train_config(cfg), dynamic_train_config(cfg)
    splat = splatting_config(cfg, 7, cfg.stage.warmup, densify=True)
    assert (static.lr_scale, static.grad_threshold, static.steps) == (0.02, 0.0003, cfg.quality.warmup_steps)
    assert (dynamic.lr_color, dynamic.steps) == (0.01, cfg.quality.dynamic_steps)
    assert dynamic.selection.enabled == cfg.stage.dynamic.select.enabled
    assert (splat.max_hops, splat.steps, splat.max_gaussians) == (8, 7, cfg.stage.warmup.max_gaussians)
    for name, _ in core_fields(WarmupTrainConfig, ("steps",)):  # nothing is left at the core's default by omission
        assert getattr(static, name) == cfg.stage.warmup[name], name
    scene = SceneDecision(model_hand=True, model_pbd=True, model_interaction=False, why={})
    arch = model_config(compose_cfg(["quality=draft", "stage.dynamic.pointnet_radii=[0.1,0.3]"]), scene)
    assert arch.pointnet_radii == (0.1, 0.3) and arch.hand_mlp and not arch.interaction
    assert arch.hand_width == cfg.quality.dynamic_width


@pytest.mark.parametrize(
    "override", ["stage.warmup.lr_opacity=fast", "stage.dynamic.lr_position=fast", "splatting.grad_threshold=fast"]
)
def test_a_hyperparameter_of_the_wrong_type_is_refused_before_any_stage(override: str) -> None:
    method = ["method=splatting_avatar"] if override.startswith("splatting") else []
    with pytest.raises(ConfigError, match=override.split("=")[0].replace(".", r"\.")):
        validate_config(compose_cfg([*method, override]), REGISTRY)


@dataclass(frozen=True)
class _Core:
    steps: int
    rate: float = 0.1  # per step
    # what it is
    name: str = "x"  # called


@dataclass
class _Own:
    extra: bool


def test_section_schema_and_core_config() -> None:
    schema = section_schema("S", _Core, exclude=("steps",), own=_Own)
    assert [f.name for f in dataclasses.fields(schema)] == ["extra", "rate", "name"]
    typed = OmegaConf.merge(OmegaConf.structured(schema), {"extra": True, "rate": 2, "name": "y"})
    assert core_config(_Core, typed, steps=3) == _Core(3, 2.0, "y")
    with pytest.raises(KeyError, match="rate: a field of _Core"):
        core_config(_Core, {"name": "y"}, steps=3)
    with pytest.raises(ValueError, match="no field"):
        section_schema("S", _Core, exclude=("nosuch",))

    @dataclass
    class Clash:
        rate: float

    with pytest.raises(ValueError, match="redefines"):
        section_schema("S", _Core, own=Clash)
