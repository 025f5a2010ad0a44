"""Batches on a real SLURM cluster (``make test-slurm``): slurmctld, slurmd, slurmdbd and munge on
localhost (:mod:`tests.cluster.local_slurm`), jobs submitted by Hydra's submitit launcher
(``hydra/launcher=slurm``), at ``quality=smoke``. Marked ``cluster``: not part of ``make test``."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from tests.cluster import batch
from tests.cluster.local_slurm import PARTITION, LocalSlurm, ensure_installed

pytestmark = pytest.mark.cluster


class SlurmLauncher:
    """The project's ``slurm`` launcher config, sized for one CPU per job on this test cluster."""

    def __init__(self, slurm: LocalSlurm) -> None:
        self.slurm = slurm

    def launcher_overrides(self) -> list[str]:
        return [
            "hydra/launcher=slurm",
            f"hydra.launcher.partition={PARTITION}",
            "hydra.launcher.cpus_per_task=1",
            "hydra.launcher.gpus_per_node=0",
            "hydra.launcher.mem_gb=6",
            "hydra.launcher.timeout_min=60",
        ]

    def env(self) -> dict[str, str]:
        return self.slurm.env()

    def job_output(self, sweep_dir: Path, driver_output: str) -> str:
        # submitit's folder (conf/hydra/launcher/slurm.yaml): <sweep>/.submitit/<job id>/<job id>_0_log.{out,err}
        return "\n".join(p.read_text(errors="replace") for p in sorted((sweep_dir / ".submitit").glob("*/*_log.*")))

    def stop_job(self, pid: int) -> str:
        environ = dict(
            v.decode().split("=", 1) for v in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0") if b"=" in v
        )
        # submitit submits a job array: the task's id as squeue, sacct and scancel write it is <array>_<index>
        job_id = (
            f"{environ['SLURM_ARRAY_JOB_ID']}_{environ['SLURM_ARRAY_TASK_ID']}"
            if "SLURM_ARRAY_JOB_ID" in environ
            else environ["SLURM_JOB_ID"]
        )
        subprocess.run(["scancel", job_id], env=self.env(), check=True)
        return job_id


@pytest.fixture(scope="module")
def slurm(tmp_path_factory: pytest.TempPathFactory):
    ensure_installed()
    with LocalSlurm(tmp_path_factory.mktemp("slurm")) as cluster:
        yield cluster


def _wait_idle(slurm: LocalSlurm, timeout_s: float = 900) -> None:
    deadline = time.monotonic() + timeout_s
    while slurm.jobs():
        assert time.monotonic() < deadline, f"jobs still queued or running: {slurm.jobs()}"
        time.sleep(1)


def _finished(slurm: LocalSlurm, timeout_s: float = 120) -> list[dict[str, str]]:
    """sacct's rows once no job is pending or running (accounting follows the jobs' ends by a moment)."""
    deadline = time.monotonic() + timeout_s
    while True:
        rows = slurm.accounting()
        if not any(r["State"] in ("PENDING", "RUNNING", "COMPLETING") for r in rows) or time.monotonic() > deadline:
            return rows
        time.sleep(1)


def _job_ids(out: Path) -> set[str]:
    """The jobs of the latest submission under ``out``: submitit's folders <array>_<index>."""
    return {p.name for p in (batch.newest_sweep(out) / ".submitit").iterdir() if "_" in p.name}


def _jobs_table(rows: list[dict[str, str]]) -> str:
    return batch.table(
        [(r["JobID"], r["State"], r["Start"], r["End"], r["Elapsed"]) for r in rows],
        ("job", "state", "start", "end", "elapsed"),
    )


def test_subjects_complete_resume_after_scancel_mid_warmup_then_are_cached(slurm: LocalSlurm, tmp_path: Path):
    story = batch.subjects_stopped_resumed_cached(SlurmLauncher(slurm), tmp_path / "out", lambda: _wait_idle(slurm))
    rows = _finished(slurm)
    states = {r["JobID"]: r["State"] for r in rows}
    assert states[story.stopped].startswith("CANCELLED"), states
    (other,) = set(batch.SUBJECTS) - {story.victim}
    assert batch.every_stage("cached", story.second, [other]) == []  # scancel of one job left the other whole
    print(
        batch.summary(
            f"SLURM: subjects; scancel {story.stopped} ({story.victim}) mid warm-up",
            {"first (one job cancelled)": story.first, "resubmitted": story.second, "submitted again": story.third},
        )
    )
    print(_jobs_table(rows))


def test_methods_fan_out_computes_the_shared_stages_once(slurm: LocalSlurm, tmp_path: Path):
    out = tmp_path / "out"
    sub = batch.methods_share_stages(SlurmLauncher(slurm), out)
    ids = _job_ids(out)
    jobs = [r for r in _finished(slurm) if r["JobID"] in ids]
    assert len(jobs) == 2 and all(j["State"] == "COMPLETED" for j in jobs), jobs
    # Both jobs ran at once (one CPU each on this node), so each shared stage was raced for.
    assert max(j["Start"] for j in jobs) < min(j["End"] for j in jobs), jobs
    print(batch.summary("SLURM: methods interactavatar,no_patch until warmup", {"methods": sub}))
    print(_jobs_table(jobs))
