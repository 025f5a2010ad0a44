"""A real local Ray cluster for the ``cluster`` tests (``make test-ray``): ``ray start --head`` on
127.0.0.1 in the Ray extra's own environment, found by the driver through ``RAY_ADDRESS``.

Ray binds to the machine's outward address unless told that this is a one-machine cluster
(``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, Ray's own switch for that); with it every Ray process
listens on 127.0.0.1 only (:meth:`LocalRay.listening` lets a test check it). ``stop`` runs ``ray stop``
and removes the session directory.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import psutil

from tests.cluster.local_slurm import ClusterError, free_port

#: RAY_DEDUP_LOGS=0: every job's lines reach the driver, none folded into "[repeated 2x]". RAY_worker_niceness=0:
#: Ray starts its task workers at nice 15; on a machine that other work keeps busy (CI, a loaded 2-core box:
#: three busy processes left them 3 % of a core, the story had not passed keypoints after 15 minutes) they
#: starve, so this one-machine cluster runs them at the priority of everything else.
LOCAL_ONLY = {
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_DEDUP_LOGS": "0",
    "RAY_worker_niceness": "0",
}


class LocalRay:
    """A one-node Ray cluster with all of this machine's CPUs and no GPU; session files under ``root``
    (keep it short: Ray's Unix sockets live there, and their paths are limited to 107 bytes)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.ray = str(Path(sys.executable).parent / "ray")

    def env(self) -> dict[str, str]:
        """The driver's environment: ``RAY_ADDRESS`` and the one-machine switches."""
        return {**os.environ, **LOCAL_ONLY, "RAY_ADDRESS": f"127.0.0.1:{self.port}"}

    def start(self) -> LocalRay:
        self.root.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(
            [
                self.ray,
                "start",
                "--head",
                "--node-ip-address=127.0.0.1",
                f"--port={self.port}",
                f"--num-cpus={os.cpu_count()}",
                "--num-gpus=0",
                "--include-dashboard=false",
                "--disable-usage-stats",
                f"--temp-dir={self.root}",
            ],
            env=self.env(),
            capture_output=True,
            text=True,
            check=False,
            timeout=180,
        )
        if done.returncode:
            self.stop()
            raise ClusterError(f"ray start failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
        return self

    def stop(self) -> None:
        subprocess.run([self.ray, "stop"], env=self.env(), capture_output=True, check=False, timeout=180)
        shutil.rmtree(self.root, ignore_errors=True)

    def listening(self) -> list[str]:
        """``ip:port`` of every socket a Ray process (whose command line names this cluster's session
        directory or port) listens on."""
        ours = set()
        for proc in psutil.process_iter(["pid", "cmdline"]):
            cmdline = " ".join(proc.info["cmdline"] or [])
            if str(self.root) in cmdline or f"{self.port}" in cmdline:
                ours.add(proc.info["pid"])
        return [
            f"{c.laddr.ip}:{c.laddr.port}"
            for c in psutil.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN and c.pid in ours
        ]

    def __enter__(self) -> LocalRay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
