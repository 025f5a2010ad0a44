"""The synthetic capture renders its sequences in parallel worker processes: the files must be the serial
run's, byte for byte, and the stage's metrics the same; a killed run leaves no worker behind."""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import pytest
import torch

from pipeline.cli import run_app
from tests.conftest import REPO, cli_command, cli_env, compose_cfg, default_sigint, wait_for

CAPTURE = importlib.import_module("stages.capture")  # the module (the package exports the stage under its name)

TINY = [
    "quality=smoke",
    "quality.capture_size=32",
    "quality.num_frames_train=2",
    "quality.num_frames_test=2",
    "stage.capture.num_cameras=2",
    "run.progress=false",
    "run.only=capture",
]


def _capture(out: Path, threads: int) -> dict[str, bytes]:
    """Run the capture stage with a torch thread budget of ``threads``; relative path -> bytes of its files."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        run_app(compose_cfg([f"paths.outputs={out}", *TINY]))
    finally:
        torch.set_num_threads(before)
    root = out / "synth_a" / "capture"
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "_manifest.json"
    }


def test_parallel_sequences_write_the_serial_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pools = []

    class CountedPool(CAPTURE.ProcessPoolExecutor):
        def __init__(self, workers: int, **kwargs: object) -> None:
            pools.append(workers)
            super().__init__(workers, **kwargs)

    monkeypatch.setattr(CAPTURE, "ProcessPoolExecutor", CountedPool)
    serial = _capture(tmp_path / "serial", threads=1)
    assert pools == []
    _capture(tmp_path / "small", threads=3)
    assert pools == []  # under PARALLEL_MIN_PIXELS: starting workers would cost more than they save
    monkeypatch.setattr(CAPTURE, "PARALLEL_MIN_PIXELS", 0)  # now this tiny capture renders in workers too
    parallel = _capture(tmp_path / "parallel", threads=3)  # three sequences: train, test, cross_synth_b
    assert pools == [3]
    assert any(name.startswith("cross_synth_b/") for name in serial)
    assert serial.keys() == parallel.keys()
    assert [name for name in serial if serial[name] != parallel[name]] == []
    metrics = [
        json.loads((tmp_path / run / "synth_a" / "capture" / "_manifest.json").read_text())["metrics"]
        for run in ("serial", "parallel")
    ]
    assert metrics[0] == metrics[1]


def _parallel_capture(tmp_path: Path, **popen: Any) -> subprocess.Popen:
    """The CLI computing a capture large enough to render in two worker processes (on any machine), into
    ``tmp_path``; ``popen``: further arguments of :class:`subprocess.Popen` (its output, its session)."""
    return subprocess.Popen(
        cli_command(
            f"paths.outputs={tmp_path}",
            "quality=smoke",
            "quality.num_frames_train=40",
            "quality.capture_size=256",
            "run.progress=false",
            "run.only=capture",
        ),
        cwd=REPO,
        env={**cli_env(), "OMP_NUM_THREADS": "2"},  # two workers on any machine
        stdout=subprocess.DEVNULL,
        preexec_fn=default_sigint,
        **popen,
    )


def test_a_killed_run_leaves_no_worker_behind(tmp_path: Path) -> None:
    """SIGKILL the CLI while its workers render: the kernel takes the workers down with it, so nothing goes on
    writing into the stage's scratch folder."""
    proc = _parallel_capture(tmp_path, stderr=subprocess.DEVNULL)
    try:
        parent = psutil.Process(proc.pid)
        # the workers have started once two children import the generator (the spawn helper is a third)
        wait_for(lambda: len(_workers(parent)) >= 2, 120)
        workers = _workers(parent)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        gone, alive = psutil.wait_procs(workers, timeout=30)
        assert alive == [] and len(gone) >= 2
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not (tmp_path / "synth_a" / "capture" / "_manifest.json").exists()


def _workers(parent: psutil.Process) -> list[psutil.Process]:
    """The worker processes of the run ``parent`` (the spawn helper's children that run ``spawn_main``)."""
    workers = []
    for child in parent.children(recursive=True):
        try:
            if "spawn_main" in " ".join(child.cmdline()):
                workers.append(child)
        except psutil.NoSuchProcess:  # ended while listed
            pass
    return workers


def _ctrl_c(tmp_path: Path, ready: Callable[[psutil.Process], bool], delay_s: float = 0.0) -> None:
    """Ctrl-C (SIGINT to the run's process group, as a terminal sends it) ``delay_s`` after ``ready(run)`` holds:
    the run says in one line what was kept, exit status 130, no traceback from it or any worker, no worker left."""
    # its own process group, as a terminal's foreground job
    proc = _parallel_capture(tmp_path, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        parent = psutil.Process(proc.pid)
        wait_for(lambda: ready(parent), 120)
        time.sleep(delay_s)
        workers = _workers(parent)
        os.killpg(proc.pid, signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
        gone, alive = psutil.wait_procs(workers, timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("interactavatar: interrupted during stage 'capture'"), stderr
    assert alive == []
    assert not (tmp_path / "synth_a" / "capture" / "_manifest.json").exists()


def test_ctrl_c_while_workers_render_is_one_line(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group, the workers too: they end quietly (no KeyboardInterrupt traceback
    per worker) and the run says in one line what was kept."""
    # both workers render once two sequences' folders are written
    _ctrl_c(tmp_path, lambda run: len(list((tmp_path / "synth_a" / ".tmp").glob("capture-*/*/videos"))) >= 2)


@pytest.mark.parametrize("delay_s", [0.0, 0.4, 1.2])
def test_ctrl_c_while_workers_start_is_one_line(tmp_path: Path, delay_s: float) -> None:
    """Ctrl-C at moments of the workers' start-up, which imports torch and the generator (seconds): as the first
    worker appears, and a little later while they import. No worker prints Python's KeyboardInterrupt."""
    _ctrl_c(tmp_path, lambda run: bool(_workers(run)), delay_s)
