"""Batches on a real local Ray cluster (``make test-ray``, in the Ray extra's own environment
``.venv-ray``): ``ray start --head`` on 127.0.0.1 (:mod:`tests.cluster.local_ray`), jobs launched by
Hydra's Ray launcher (``hydra/launcher=ray_cluster``), at ``quality=smoke``. Marked ``cluster``."""

from __future__ import annotations

import importlib.util
import ipaddress
import os
import signal
import tempfile
import time
from pathlib import Path

import psutil
import pytest

from tests.cluster import batch
from tests.cluster.local_ray import LocalRay

pytestmark = pytest.mark.cluster


class RayLauncher:
    """The project's ``ray_cluster`` launcher config, one CPU per job; ``max_retries=0`` so that a killed
    worker fails its job (Ray's default is to rerun it, which would resume it from its checkpoint unasked)."""

    def __init__(self, cluster: LocalRay) -> None:
        self.cluster = cluster

    def launcher_overrides(self) -> list[str]:
        return [
            "hydra/launcher=ray_cluster",
            "hydra.launcher.ray.remote.num_cpus=1",
            "hydra.launcher.ray.remote.num_gpus=0",
            "+hydra.launcher.ray.remote.max_retries=0",
        ]

    def env(self) -> dict[str, str]:
        return self.cluster.env()

    def job_output(self, sweep_dir: Path, driver_output: str) -> str:
        return driver_output  # Ray forwards every worker's output to the driver, prefixed "(_run_job pid=...)"

    def stop_job(self, pid: int) -> str:
        os.kill(pid, signal.SIGKILL)  # a lost worker: what a preempted or failed node does to a Ray task
        return f"worker {pid} killed"


@pytest.fixture(scope="module")
def ray_cluster():
    if importlib.util.find_spec("ray") is None or importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None:
        pytest.fail("the Ray test runs in the Ray extra's environment: make test-ray")
    with LocalRay(Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))) as cluster:
        yield cluster


def _wait_idle(timeout_s: float = 300) -> None:
    """Until no Ray worker runs a job (a driver that gives up takes its tasks with it, Ray kills them)."""
    deadline = time.monotonic() + timeout_s
    while any("ray::_run_job" in " ".join(p.info["cmdline"] or []) for p in psutil.process_iter(["cmdline"])):
        assert time.monotonic() < deadline, "a Ray worker still runs a job"
        time.sleep(1)


def test_ray_listens_on_loopback_only(ray_cluster: LocalRay):
    sockets = ray_cluster.listening()
    assert sockets, "found no Ray process"
    assert all(ipaddress.ip_address(s.rsplit(":", 1)[0].removeprefix("::ffff:")).is_loopback for s in sockets), sockets


def test_subjects_complete_resume_after_a_killed_worker_then_are_cached(ray_cluster: LocalRay, tmp_path: Path):
    story = batch.subjects_stopped_resumed_cached(RayLauncher(ray_cluster), tmp_path / "out", _wait_idle)
    print(
        batch.summary(
            f"Ray: subjects; {story.stopped} ({story.victim}) mid warm-up",
            {"first (one worker killed)": story.first, "resubmitted": story.second, "submitted again": story.third},
        )
    )


def test_methods_fan_out_computes_the_shared_stages_once(ray_cluster: LocalRay, tmp_path: Path):
    sub = batch.methods_share_stages(RayLauncher(ray_cluster), tmp_path / "out")
    print(batch.summary("Ray: methods interactavatar,no_patch until warmup", {"methods": sub}))
