"""Build and load the compiled CPU rasterizer (``csrc/rasterizer_cpu.cpp``) as torch operators.

The extension is a torch C++ extension built with ``torch.utils.cpp_extension.load`` (ninja,
the host g++, OpenMP from torch's own ``libgomp``) into ``csrc/build/`` next to the sources,
which git ignores. ``make run`` / ``make test`` build it once at install time (``main``);
afterwards loading it is a no-op ninja check.
Editing the source rebuilds it on the next load. A failed build is recorded with the hash of
what it tried to build, so later processes do not retry the same failing build: they warn once
(per process) and the ``auto`` backend falls back to ``torch``.

The operators live in ``torch.ops.interactavatar_gs`` (see ``backend_cpu``).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import shutil
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import torch
from filelock import FileLock

NAME = "interactavatar_gs_cpu"
CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (CSRC / "rasterizer_cpu.cpp",)
BUILD_DIR = CSRC / "build"
#: -march=native: the library is built on the machine that runs it. -ffp-contract=off: no fused
#: multiply-adds, so every loop rounds the same way whatever the compiler vectorises.
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fopenmp")
#: -fopenmp links libgomp.so.1, which resolves to the copy torch has already loaded: one thread
#: pool, sized by ``torch.set_num_threads``.
LDFLAGS = ("-fopenmp",)
_FAILED = BUILD_DIR / "build_failed.txt"


def _build_key() -> str:
    """Hash of everything the build depends on: sources, flags, torch version, compiler."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.read_bytes())
    digest.update(repr((CFLAGS, LDFLAGS, torch.__version__, shutil.which("c++"))).encode())
    return digest.hexdigest()


@contextlib.contextmanager
def _ninja_on_path() -> Iterator[None]:
    """Put the virtual environment's ``bin`` (where the pinned ``ninja`` wheel installs) on PATH
    while building: ``cpp_extension`` runs ``ninja`` from PATH, and ``.venv/bin/python`` run
    directly does not add its own ``bin``."""
    old = os.environ.get("PATH", "")
    os.environ["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), old])
    try:
        yield
    finally:
        os.environ["PATH"] = old


def build(verbose: bool = False) -> Path:
    """Build the extension if its sources changed, load its operators, return the library path.

    Raises whatever the build raises; a failure is recorded in ``csrc/build/build_failed.txt``
    and raised again, without rebuilding, until the sources, flags, torch or compiler change.
    """
    from torch.utils import cpp_extension

    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    key = _build_key()
    with FileLock(str(BUILD_DIR / "build.lock")):
        if _FAILED.exists() and _FAILED.read_text().split("\n", 1)[0] == key:
            raise RuntimeError(f"an earlier build of these sources failed; see {_FAILED}")
        # cpp_extension's own lock file: it is stale whenever we hold ours (a killed build left it).
        (BUILD_DIR / "lock").unlink(missing_ok=True)
        try:
            with _ninja_on_path():
                path = cpp_extension.load(name=NAME, sources=[str(s) for s in SOURCES],
                                          build_directory=str(BUILD_DIR), extra_cflags=list(CFLAGS),
                                          extra_ldflags=list(LDFLAGS), is_python_module=False, verbose=verbose)
        except Exception as exc:
            _FAILED.write_text(f"{key}\n{type(exc).__name__}: {exc}\n")
            raise
        _FAILED.unlink(missing_ok=True)
    return Path(path)


@functools.cache
def unavailable_reason() -> str | None:
    """None once the compiled backend is loaded in this process, else why it is not (warned once)."""
    try:
        build()
    except Exception as exc:  # any build or load failure means: use the torch backend
        first_line = (str(exc).strip().splitlines() or [""])[0]
        reason = f"{type(exc).__name__}: {first_line} (build log: {_FAILED})"
        warnings.warn(f"the compiled CPU Gaussian rasterizer is unavailable, using the torch backend: {reason}",
                      RuntimeWarning, stacklevel=2)
        return reason
    return None


def cpu_extension_available() -> bool:
    """True when the compiled CPU backend is built and loaded (builds it on first call)."""
    return unavailable_reason() is None


def main() -> None:
    """Build the extension now and say how it went (``make`` calls this at install time)."""
    start = time.perf_counter()
    reason = unavailable_reason()
    if reason is None:
        print(f"compiled CPU rasterizer ready ({time.perf_counter() - start:.0f} s): {BUILD_DIR / NAME}.so")
    else:
        print(f"compiled CPU rasterizer NOT built, the torch backend will be used: {reason}")
