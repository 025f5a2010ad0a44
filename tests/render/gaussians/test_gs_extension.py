"""Building and loading the compiled CPU rasterizer: a failed build is recorded and not retried,
it warns once, and ``auto`` falls back to the torch backend."""

from __future__ import annotations

import re
import subprocess
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
    monkeypatch.setattr(extension, "BUILD_ROOT", tmp_path / "build")
    extension.unavailable_reason.cache_clear()
    yield extension.build_dir()
    extension.unavailable_reason.cache_clear()


def test_a_failed_build_is_recorded_and_not_retried(broken_build: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(RuntimeError, match="Error building extension"):
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


def test_each_kind_of_cpu_builds_into_its_own_folder(monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkout shared by machines whose -march=native differs (cluster nodes) must not load another
    machine's library: the build folder is named after the instruction set the compiler targets here."""
    tag = extension.target_tag()
    assert re.fullmatch(r"[A-Za-z0-9_.-]+-[0-9a-f]{10}", tag), tag
    assert extension.build_dir() == extension.BUILD_ROOT / tag

    key = extension._build_key()
    listing = "  -march=                     \t\tskylake-avx512\n  -mavx512f                   \t\t[enabled]\n"
    monkeypatch.setattr(extension.subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0, listing, ""))
    extension.target_tag.cache_clear()
    try:
        other = extension.target_tag()
        assert other.startswith("skylake-avx512-") and other != tag
        assert extension.build_dir() != extension.BUILD_ROOT / tag
        assert extension._build_key() != key
    finally:
        monkeypatch.undo()
        extension.target_tag.cache_clear()
    assert extension.target_tag() == tag
