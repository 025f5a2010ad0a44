"""One definition per setting (issue 37): the config sections that feed a training loop are typed by the loop's own
config dataclass, set every one of its hyperparameters, and default to its values unless the pipeline chooses
otherwise for a reason stated here."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest
from omegaconf import OmegaConf

from avatar.dynamic.model import DynamicModelConfig
from avatar.scene import SceneDecision
from avatar.training.dynamic import DynamicTrainConfig
from avatar.training.splatting import SplattingConfig
from avatar.training.static import StaticConfig
from pipeline.config import ConfigError, validate_config
from pipeline.schema import core_config, core_fields, section_schema
from stages import REGISTRY
from stages.dynamic import DynamicConfig
from stages.representations.bound import PRESET_ARCHITECTURE, dynamic_train_config, model_config, static_config
from stages.representations.embedded import SHARED_SCHEDULE, SplattingSchema, splatting_config
from stages.warmup import WarmupConfig
from tests.conftest import CONF_DIR, compose_cfg

#: Where the pipeline's default differs from the core's, and why.
PIPELINE_CHOICES = {
    "checkpoint_every": "the pipeline checkpoints so that a killed run resumes; the core, a library, does not",
    "seed": "the run's seed (root key seed)",
}

#: (core dataclass, the file and key of its config section, its fields the section does not hold, the section's
#: schema)
SECTIONS = [
    (StaticConfig, "stage/warmup.yaml", "stage.warmup", ("steps",), WarmupConfig),
    (DynamicTrainConfig, "stage/dynamic.yaml", "stage.dynamic", ("steps", "selection"), DynamicConfig),
    (DynamicModelConfig, "stage/dynamic.yaml", "stage.dynamic", PRESET_ARCHITECTURE, DynamicConfig),
    (SplattingConfig, "config.yaml", "splatting", SHARED_SCHEDULE, SplattingSchema),
]


@pytest.mark.parametrize(
    ("core", "file", "key", "exclude", "schema"), SECTIONS, ids=[f"{s[2]}-{s[0].__name__}" for s in SECTIONS]
)
def test_each_section_sets_every_hyperparameter_of_its_loop_at_the_loops_default(
    core, file, key, exclude, schema
) -> None:
    loaded = OmegaConf.load(CONF_DIR / file)  # the defaults, before any preset's choices
    section = loaded if file.startswith("stage/") else loaded[key]
    defaults = {f.name: f.default for f in dataclasses.fields(core)}
    for name, _ in core_fields(core, exclude):
        assert name in section, f"{key}.{name}: a hyperparameter of {core.__name__} that the config cannot set"
        assert name in {f.name for f in dataclasses.fields(schema)}, f"{schema.__name__} does not type {name}"
        if name not in PIPELINE_CHOICES:
            value = tuple(section[name]) if isinstance(defaults[name], tuple) else section[name]
            assert value == defaults[name], (
                f"{key}.{name}={section[name]} but {core.__name__}.{name} defaults to {defaults[name]}: one default "
                f"per setting (change both, or state the pipeline's reason in PIPELINE_CHOICES)"
            )


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
    static, dynamic = static_config(cfg), dynamic_train_config(cfg)
    splat = splatting_config(cfg, 7, cfg.stage.warmup, densify=True)
    assert (static.lr_scale, static.grad_threshold, static.steps) == (0.02, 0.0003, cfg.quality.warmup_steps)
    assert (dynamic.lr_color, dynamic.steps) == (0.01, cfg.quality.dynamic_steps)
    assert dynamic.selection.enabled == cfg.stage.dynamic.select.enabled
    assert (splat.max_hops, splat.steps, splat.max_gaussians) == (8, 7, cfg.stage.warmup.max_gaussians)
    for name, _ in core_fields(StaticConfig, ("steps",)):  # nothing is left at the core's default by omission
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
    rate: float = 0.1
    name: str = "x"


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
