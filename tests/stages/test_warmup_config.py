"""``stage.warmup`` is range-checked before any stage runs: values that would degrade silently are refused."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from avatar.representations.bound.gaussians import BoundGaussians
from pipeline.cli import run_app
from pipeline.config import ConfigError
from stages.warmup import WarmupConfig
from tests.conftest import compose_cfg

BAD_OPACITIES = ["0", "1", "1.5", "nan"]


@pytest.mark.parametrize("value", BAD_OPACITIES)
def test_init_opacity_outside_the_open_unit_interval_fails_before_any_stage(tmp_path: Path, value: str):
    # 0 and 1 give infinite opacity logits, which training used to reset silently.
    cfg = compose_cfg(
        [
            f"paths.outputs={tmp_path / 'out'}",
            "run.progress=false",
            "run.dry=true",
            f"stage.warmup.init_opacity={value}",
        ]
    )
    with pytest.raises(ConfigError) as info:
        run_app(cfg)
    lines = [line for line in str(info.value).splitlines() if "init_opacity" in line]
    assert len(lines) == 1, str(info.value)
    assert "stage.warmup" in lines[0] and "must lie strictly between 0 and 1" in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", [0.0, 1.0, float("nan")])
def test_warmup_config_checks_its_range(value: float):
    base = OmegaConf.to_container(compose_cfg([]).stage.warmup, resolve=True)
    assert WarmupConfig.validate(OmegaConf.create(base)) == []
    merged = OmegaConf.merge(OmegaConf.structured(WarmupConfig), {**base, "init_opacity": value})
    assert len(WarmupConfig.validate(merged)) == 1
    with pytest.raises(ValueError, match="init_opacity=.*must lie strictly between 0 and 1"):
        OmegaConf.to_object(merged)  # builds the dataclass: __post_init__ checks it too


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_gaussians_refuse_an_opacity_with_an_infinite_logit(value: float):
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float32)
    with pytest.raises(ValueError, match="init_opacity must lie strictly between 0 and 1"):
        BoundGaussians.on_triangles(verts, torch.tensor([[0, 1, 2]]), torch.tensor([0]), 1, init_opacity=value)
