"""Build and load the compiled CPU rasterizer (``csrc/rasterizer_cpu.cpp``) as torch operators.

The extension is a torch C++ extension built with ``torch.utils.cpp_extension.load`` (ninja,
the host g++, OpenMP from torch's own ``libgomp``) into ``csrc/build/<target>/`` next to the
sources, which git ignores. ``<target>`` names the instruction set ``-march=native`` selects on
this machine (:func:`target_tag`): a checkout on a file system that several kinds of machine share
(cluster nodes) keeps one build per kind, instead of loading a library built for another CPU
(which can die on an illegal instruction, with no fallback). ``make run`` / ``make test`` build
it at install time (``main``); afterwards loading it is a no-op ninja check.
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
import re
import shutil
import subprocess
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
BUILD_ROOT = CSRC / "build"
#: -march=native: the library is built on the machine that runs it. -ffp-contract=off: no fused
#: multiply-adds, so every loop rounds the same way whatever the compiler vectorises.
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fopenmp")
#: -fopenmp links libgomp.so.1, which resolves to the copy torch has already loaded: one thread
#: pool, sized by ``torch.set_num_threads``.
LDFLAGS = ("-fopenmp",)


def _compiler() -> str:
    """The C++ compiler ``cpp_extension`` builds with: ``$CXX``, else ``c++``."""
    return os.environ.get("CXX", "c++")


@functools.cache
def target_tag() -> str:
    """``<arch>-<hash>``: the ``-march=`` that ``-march=native`` resolves to on this machine and a hash of
    every target option it enables (``c++ -march=native -Q --help=target``, ~20 ms), so two CPUs of one
    family with different extensions (e.g. with and without AVX-512) get different tags. ``unknown``
    when the compiler cannot be asked (the build then fails and says why)."""
    try:
        listing = subprocess.run(
            [_compiler(), "-march=native", "-Q", "--help=target"],
            capture_output=True,
            text=True,
            check=True,
            timeout=60,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    arch = re.search(r"^\s*-march=\s+(\S+)", listing, re.MULTILINE)
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", arch.group(1)) if arch else "native"
    return f"{name}-{hashlib.sha256(listing.encode()).hexdigest()[:10]}"


def build_dir() -> Path:
    """Where this machine's build lives: ``csrc/build/<target_tag()>``."""
    return BUILD_ROOT / target_tag()


def _failed_record() -> Path:
    return build_dir() / "build_failed.txt"


def _build_key() -> str:
    """Hash of everything the build depends on: sources, flags, torch version, compiler."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.read_bytes())
    digest.update(repr((CFLAGS, LDFLAGS, torch.__version__, shutil.which(_compiler()), target_tag())).encode())
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

    Raises whatever the build raises; a failure is recorded in ``build_dir()/build_failed.txt``
    and raised again, without rebuilding, until the sources, flags, torch or compiler change.
    """
    from torch.utils import cpp_extension

    folder, failed = build_dir(), _failed_record()
    folder.mkdir(parents=True, exist_ok=True)
    key = _build_key()
    with FileLock(str(folder / "build.lock")):
        if failed.exists() and failed.read_text().split("\n", 1)[0] == key:
            raise RuntimeError(f"an earlier build of these sources failed; see {failed}")
        # cpp_extension's own lock file: it is stale whenever we hold ours (a killed build left it).
        (folder / "lock").unlink(missing_ok=True)
        try:
            with _ninja_on_path():
                path = cpp_extension.load(
                    name=NAME,
                    sources=[str(s) for s in SOURCES],
                    build_directory=str(folder),
                    extra_cflags=list(CFLAGS),
                    extra_ldflags=list(LDFLAGS),
                    is_python_module=False,
                    verbose=verbose,
                )
        except Exception as exc:
            failed.write_text(f"{key}\n{type(exc).__name__}: {exc}\n")
            raise
        failed.unlink(missing_ok=True)
    return Path(path)


@functools.cache
def unavailable_reason() -> str | None:
    """None once the compiled backend is loaded in this process, else why it is not (warned once)."""
    try:
        build()
    except Exception as exc:  # any build or load failure means: use the torch backend
        first_line = (str(exc).strip().splitlines() or [""])[0]
        reason = f"{type(exc).__name__}: {first_line} (build log: {_failed_record()})"
        warnings.warn(
            f"the compiled CPU Gaussian rasterizer is unavailable, using the torch backend: {reason}",
            RuntimeWarning,
            stacklevel=2,
        )
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
        print(f"compiled CPU rasterizer ready ({time.perf_counter() - start:.0f} s): {build_dir() / NAME}.so")
    else:
        print(f"compiled CPU rasterizer NOT built, the torch backend will be used: {reason}")
