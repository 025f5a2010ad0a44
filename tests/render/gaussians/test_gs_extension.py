"""Building and loading the compiled CPU rasterizer: a failed build is recorded and not retried,
it warns once, and ``auto`` falls back to the torch backend."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from avatar.render.gaussians import extension
from avatar.render.gaussians.render import available_backends, resolve_backend


@pytest.fixture
def broken_build(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The extension pointed at a source that does not compile, in a scratch build directory; the
    process-wide load state is restored afterwards."""
    source = tmp_path / "broken.cpp"
    source.write_text("#error this source does not compile\n")
    monkeypatch.setattr(extension, "SOURCES", (source,))
    monkeypatch.setattr(extension, "NAME", "interactavatar_gs_broken")
    monkeypatch.setattr(extension, "BUILD_DIR", tmp_path / "build")
    monkeypatch.setattr(extension, "_FAILED", tmp_path / "build" / "build_failed.txt")
    extension.unavailable_reason.cache_clear()
    yield tmp_path / "build"
    extension.unavailable_reason.cache_clear()


def test_a_failed_build_is_recorded_and_not_retried(broken_build: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(Exception):
        extension.build()
    failed = broken_build / "build_failed.txt"
    assert failed.read_text().split("\n", 1)[0] == extension._build_key()
    assert "does not compile" in failed.read_text()

    from torch.utils import cpp_extension

    monkeypatch.setattr(cpp_extension, "load", lambda **_: pytest.fail("retried a recorded failed build"))
    with pytest.raises(RuntimeError, match="an earlier build of these sources failed"):
        extension.build()


def test_unavailable_extension_warns_once_and_auto_uses_torch(broken_build: Path) -> None:
    with pytest.warns(RuntimeWarning, match="compiled CPU Gaussian rasterizer is unavailable, using the torch"):
        assert not extension.cpu_extension_available()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a second warning would raise here
        assert "cpu" not in available_backends()
        assert resolve_backend("auto", torch.zeros(1, 3)) == "torch"
        with pytest.raises(RuntimeError, match="backend 'cpu' .* is unavailable"):
            resolve_backend("cpu", torch.zeros(1, 3))
