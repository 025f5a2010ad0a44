"""The model files a config names (``model.flame_path``, ``mano_path``, ``face_stiffness_path``) are checked
before any stage runs: a missing or misnamed file is one line naming the key and the fix, and nothing runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from tests.conftest import compose_cfg


def _run(tmp_path: Path, *extra: str) -> None:
    run_app(compose_cfg([f"paths.outputs={tmp_path / 'out'}", "run.progress=false", *extra]))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("model.face_stiffness_path={tmp}/missing.npy", "model.face_stiffness_path={tmp}/missing.npy: no such file"),
        ("model.face_stiffness_path={tmp}/thickness.txt", "must be a .npy file of skin thicknesses"),
        ("model.flame_path={tmp}/generic_model.pkl", "model.flame_path={tmp}/generic_model.pkl: no such file"),
        ("model.mano_path={tmp}", "model.mano_path={tmp}: no such file"),
    ],
)
def test_a_model_file_that_cannot_be_read_is_refused_before_any_stage(tmp_path, override: str, message: str) -> None:
    (tmp_path / "thickness.txt").write_text("0.01\n")
    for extra in (["run.dry=true"], []):
        with pytest.raises(ConfigError) as caught:
            _run(tmp_path, override.format(tmp=tmp_path), *extra)
        assert message.format(tmp=tmp_path) in str(caught.value)
        assert not (tmp_path / "out" / "synth_a").exists()


def test_a_stiffness_file_that_exists_passes_the_check(tmp_path) -> None:
    (tmp_path / "thickness.npz").write_bytes(b"")
    _run(tmp_path, f"model.face_stiffness_path={tmp_path / 'thickness.npz'}", "run.dry=true")
