"""``stage.dynamic`` and the preset's stage-two sizes are range-checked before any stage runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from tests.conftest import compose_cfg

BAD = [
    ("stage.dynamic.contact_fraction=1.5", "contact_fraction=1.5: must lie in [0, 1]"),
    ("stage.dynamic.contact_fraction=nan", "contact_fraction=nan: must lie in [0, 1]"),
    ("stage.dynamic.max_contact_emphasis=0.5", "max_contact_emphasis=0.5: must be >= 1 and finite"),
    ("stage.dynamic.max_contact_emphasis=nan", "max_contact_emphasis=nan: must be >= 1 and finite"),
    ("stage.dynamic.max_contact_emphasis=inf", "max_contact_emphasis=inf: must be >= 1 and finite"),
    ("stage.dynamic.restarts=0", "restarts=0: must be >= 1"),
    ("stage.dynamic.validation.fraction=1.0", "validation.fraction=1: must lie strictly between 0 and 1"),
    ("stage.warmup.validation.fraction=nan", "validation.fraction=nan: must lie strictly between 0 and 1"),
    ("stage.dynamic.validation.min_train_frames=0", "validation.min_train_frames=0: must be >= 1"),
    ("stage.dynamic.colour_delta=multiply", "colour_delta=multiply: must be one of add, scale"),
    ("stage.dynamic.d_max=0", "d_max=0: must be positive"),
    ("stage.dynamic.d_max=-0.05", "d_max=-0.05: must be positive"),
    ("quality.dynamic_width=0", "dynamic_width=0: must be between 1 and 4096"),
    ("quality.pointnet_centres=[64]", "pointnet_centres=[64]: must be two positive counts"),
]


@pytest.mark.parametrize(("override", "message"), BAD)
def test_bad_stage_two_settings_fail_before_any_stage(tmp_path: Path, override: str, message: str) -> None:
    cfg = compose_cfg([f"paths.outputs={tmp_path / 'out'}", "run.progress=false", "run.dry=true", override])
    with pytest.raises(ConfigError) as info:
        run_app(cfg)
    lines = [line for line in str(info.value).splitlines() if message in line]
    assert len(lines) == 1, str(info.value)
    assert override.split("=")[0].rsplit(".", 1)[0] in lines[0], lines[0]  # names the section
    assert not (tmp_path / "out").exists()
