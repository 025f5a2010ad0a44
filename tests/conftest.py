"""Shared fixtures: composing the real config tree, and running the CLI in a subprocess."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from pipeline.threads import wait_passively


def _share_the_cores_between_workers() -> None:
    """Under pytest-xdist (``make test`` runs one worker per core, ``-n auto``), each worker and the runs it starts use
    their share of the cores (``OMP_NUM_THREADS``, unless the caller set it): a worker's torch taking every core, and
    the other worker's too, made each slower than alone. Set before torch loads, like :func:`wait_passively`."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1 and "OMP_NUM_THREADS" not in os.environ:
        os.environ["OMP_NUM_THREADS"] = str(max(1, len(os.sched_getaffinity(0)) // workers))


# Idle OpenMP threads sleep in the suite's own process, as in the runs it starts (pipeline.launch): the runtime reads
# this when torch loads, which is after this file (torch is imported by the test modules and the fixtures below).
wait_passively()
_share_the_cores_between_workers()

#: The test files that take longest (minutes on 2 cores: ``pytest --durations``), started first so that under
#: pytest-xdist (``--dist loadfile``: a file's tests stay on one worker) no worker is left with one of them at the end.
LONGEST_FIRST = (
    "tests/test_end_to_end.py",
    "tests/test_extremes_dag.py",
    "tests/stages/test_train_refinement.py",
    "tests/stages/test_keypoints_fit.py",
    "tests/test_monocular_dag.py",
    "tests/stages/test_dynamic_selection.py",
    "tests/stages/test_capture_parallel.py",
    "tests/pipeline/test_numeric_settings.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The files of :data:`LONGEST_FIRST` first, in its order; the rest as collected."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}

    def key(item: pytest.Item) -> int:
        return rank.get(Path(item.fspath).relative_to(REPO).as_posix(), len(rank))

    items.sort(key=key)  # stable: within a file and among the rest, the collected order


REPO = Path(__file__).resolve().parent.parent
CONF_DIR = REPO / "conf"
TOY_OVERRIDES = ["pipeline.stages_module=tests.toy_dag", "stage=[]"] + [f"+stage.{n}.value=1" for n in "abcd"]


def compose_cfg(overrides: Sequence[str]) -> DictConfig:
    """The app's config as Hydra composes it for these command-line overrides."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture
def toy_cfg(tmp_path: Path) -> Callable[..., DictConfig]:
    """Compose a config for the toy DAG writing under tmp_path, plus extra overrides."""

    def make(*extra: str) -> DictConfig:
        return compose_cfg([*TOY_OVERRIDES, f"paths.outputs={tmp_path / 'out'}", "run.progress=false", *extra])

    return make


def cli_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def cli_command(*args: str) -> list[str]:
    """``interactavatar`` with these arguments, through the console script's own entry point."""
    return [sys.executable, "-m", "pipeline.launch", *args]


def run_cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """Run ``interactavatar`` with these arguments from the repo root."""
    return subprocess.run(
        cli_command(*args), cwd=REPO, env=cli_env(), capture_output=True, text=True, timeout=timeout, check=False
    )


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Run a test on one torch thread: many small tensor ops gain nothing from threads, and lose
    badly on a busy machine. Directories opt in through an autouse fixture in their conftest."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def default_sigint() -> None:
    """``preexec_fn`` of a child that a test interrupts with SIGINT: Ctrl-C's default action, as in a terminal's
    foreground job. A suite run as a background shell job (``cmd &``, ``nohup``) ignores SIGINT, its children
    inherit that, and Python then never raises KeyboardInterrupt in them."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def wait_for(predicate: Callable[[], bool], timeout_s: float = 60.0) -> None:
    """Poll ``predicate`` every 50 ms until it holds; ``TimeoutError`` after ``timeout_s``."""
    deadline = time.time() + timeout_s
    while not predicate():
        if time.time() > deadline:
            raise TimeoutError("condition not met in time")
        time.sleep(0.05)


def record_crop_reads(monkeypatch: pytest.MonkeyPatch, capture_dir: Path) -> tuple[list[Path], list[str]]:
    """(every image path the stages read through ``avatar.artifacts.read_png`` from now on, the capture's held-out
    camera ids): a test that the held-out camera is never read checks that no path names one of them."""
    import avatar.artifacts
    from data_schemas.cameras import read_cameras
    from data_schemas.images import read_png

    held_out = [c.camera_id for c in read_cameras(capture_dir / "cameras.parquet") if c.split == "test"]
    assert held_out, f"{capture_dir}: no held-out camera to check"
    read: list[Path] = []

    def recording_read_png(path, channels):  # read_png's signature
        read.append(Path(path))
        return read_png(path, channels)

    monkeypatch.setattr(avatar.artifacts, "read_png", recording_read_png)
    return read, held_out


@contextmanager
def small_disk(mount: Path, size_kib: int) -> Iterator[Path]:
    """A tmpfs of ``size_kib`` KiB mounted on the empty folder ``mount`` (made here), unmounted afterwards; the
    test is skipped where mounting is not allowed (needs root)."""
    mount.mkdir(parents=True)
    try:
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(mount)], capture_output=True, check=False
        )
    except OSError:
        done = None
    if done is None or done.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        yield mount
    finally:
        if subprocess.run(["umount", str(mount)], check=False).returncode != 0:
            subprocess.run(["umount", "-l", str(mount)], check=False)


def fill_disk(mount: Path, leave_kib: int = 0) -> None:
    """Fill the disk of ``mount`` with a file ``mount/filler`` until ``leave_kib`` KiB are free (or fewer)."""
    free = os.statvfs(mount).f_bavail * os.statvfs(mount).f_frsize - leave_kib * 1024
    with open(mount / "filler", "wb") as f:
        try:
            f.write(b"\xff" * max(free, 0))
        except OSError:  # the last block did not fit: the disk is full
            pass
