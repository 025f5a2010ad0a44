"""What a batch run on a real cluster must show, the same for every launcher (SLURM, Ray).

A :class:`Cluster` submits ``interactavatar -m ...`` through its launcher and stops one job the way its
scheduler does; the checks here read only what the pipeline leaves on disk (manifests, checkpoints,
locks) and what the jobs printed.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import psutil

from pipeline.manifest import read_manifest, verify_outputs
from stages import REGISTRY
from tests.conftest import REPO, cli_command, cli_env

SMOKE = ("quality=smoke", "run.progress=false")
# The story stops a job at its first warm-up checkpoint: at step 10, not 50 (not in the cache key).
EARLY_CHECKPOINT = "stage.warmup.checkpoint_every=10"
#: The story's warm-up: 1500 steps (smoke's 150 took 4 s on the loaded 2-core machine, and the 140 after the first
#: checkpoint fitted into the window between SLURM's SIGCONT and its SIGKILL: 2 runs in 7 on 2026-12-06).
LONG_WARMUP = "quality.warmup_steps=1500"
SUBJECTS = ("synth_a", "synth_b")
# One decision line of the runner: "[synth_a] capture    run       <reason>" (per-method: "[synth_a/<method>]").
DECISION = re.compile(
    r"\[(?P<subject>[\w-]+)(?:/(?P<method>[\w-]+))?\] "
    r"(?P<stage>\w+)\s+(?P<action>run|cached|shared)\b"
)


class Cluster(Protocol):
    """A launcher on a running cluster."""

    def launcher_overrides(self) -> list[str]:
        """``hydra/launcher=...`` and the overrides that size a job for this test (one CPU each)."""

    def env(self) -> dict[str, str]:
        """The environment the ``interactavatar`` driver needs to reach the cluster."""

    def job_output(self, sweep_dir: Path, driver_output: str) -> str:
        """Everything the jobs of one submission printed, concatenated."""

    def stop_job(self, pid: int) -> str:
        """Stop the job whose process ``pid`` is the scheduler's way (scancel, a killed worker); says what."""


@dataclass
class Submission:
    """One ``interactavatar -m`` run through a cluster launcher."""

    returncode: int
    driver_output: str  # the driver's stdout and stderr
    job_output: str  # what its jobs printed
    wall_s: float

    def decisions(self) -> Counter[tuple[str, str | None, str, str]]:
        """How often each (subject, method, stage, action) was printed by the jobs."""
        return Counter((m["subject"], m["method"], m["stage"], m["action"]) for m in DECISION.finditer(self.job_output))


def start(cluster: Cluster, out: Path, sweep: Sequence[str], *extra: str) -> subprocess.Popen[str]:
    """Start ``interactavatar -m <sweep>`` on ``cluster``, writing under ``out`` (returns at once)."""
    args = ["-m", *sweep, *cluster.launcher_overrides(), *SMOKE, f"paths.outputs={out}", *extra]
    return subprocess.Popen(
        cli_command(*args),
        cwd=REPO,
        env={**cli_env(), **cluster.env()},
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def finish(
    cluster: Cluster, out: Path, proc: subprocess.Popen[str], started: float, timeout_s: float = 1800
) -> Submission:
    """Wait for the submission ``proc`` and collect what its jobs printed."""
    driver_output, _ = proc.communicate(timeout=timeout_s)
    wall = time.monotonic() - started
    return Submission(proc.returncode, driver_output, cluster.job_output(newest_sweep(out), driver_output), wall)


def submit(cluster: Cluster, out: Path, sweep: Sequence[str], *extra: str) -> Submission:
    """``interactavatar -m <sweep>`` on ``cluster``, waited for."""
    started = time.monotonic()
    return finish(cluster, out, start(cluster, out, sweep, *extra), started)


def newest_sweep(out: Path) -> Path:
    """The sweep directory of the latest multirun under ``out`` (Hydra names them by time)."""
    sweeps = sorted((out / "_hydra" / "multirun").iterdir())
    assert sweeps, f"no multirun under {out}"
    return sweeps[-1]


def _warmup_lock(out: Path, subject: str) -> Path:
    return out / subject / ".locks" / "warmup@interactavatar.lock"


def holder_of_lock(lock: Path) -> int:
    """The process id that holds ``lock`` open (a running stage keeps its lock file open)."""
    for proc in psutil.process_iter(["pid"]):
        try:
            if any(Path(f.path) == lock for f in proc.open_files()):
                return proc.pid
        except (psutil.AccessDenied, psutil.NoSuchProcess, psutil.ZombieProcess):
            continue
    raise LookupError(f"no process holds {lock}")


def stop_mid_warmup(cluster: Cluster, out: Path, subject: str, timeout_s: float = 1200) -> str:
    """Stop the job of ``subject`` at its warm-up's first checkpoint, while it is in warm-up; says what was done.

    The job's process is looked up while its warm-up starts, frozen (SIGSTOP) the moment the checkpoint
    appears, then stopped the scheduler's way. The scheduler resumes it first (SLURM sends SIGCONT, then SIGTERM,
    which submitit ignores, and SIGKILL only once its step has not ended within a few seconds, more under load), so
    the story's warm-up is long (:data:`LONG_WARMUP`): what is left of it after the first checkpoint takes far longer
    than that window."""
    pid = None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pid is None and _warmup_lock(out, subject).exists():
            try:
                pid = holder_of_lock(_warmup_lock(out, subject))
            except LookupError:
                pass
        if any((out / subject / ".scratch").glob("warmup*/warmup.pt")):
            pid = pid or holder_of_lock(_warmup_lock(out, subject))
            os.kill(pid, signal.SIGSTOP)
            assert not (out / subject / "methods" / "interactavatar" / "warmup" / "_manifest.json").exists(), (
                "the warm-up finished before its job was frozen: lower stage.warmup.checkpoint_every"
            )
            return cluster.stop_job(pid)
        time.sleep(0.1)
    raise TimeoutError(f"no warm-up checkpoint of {subject} under {out} after {timeout_s} s")


def whole_manifests(out: Path, subject: str) -> list[str]:
    """Every stage of ``subject`` (method interactavatar) whose artifact is missing or not whole; [] when
    all are."""
    problems = []
    for stage in REGISTRY:
        where = out / subject / ("methods/interactavatar/" if stage.per_method else "") / stage.name
        manifest = read_manifest(where)
        problem = "no manifest" if manifest is None else verify_outputs(where, manifest, stage.outputs)
        if problem:
            problems.append(f"{subject}/{stage.name}: {problem}")
    return problems


def warmup_metrics(out: Path, subject: str) -> dict[str, object]:
    """The manifest metrics of ``subject``'s warm-up (method interactavatar)."""
    manifest = read_manifest(out / subject / "methods" / "interactavatar" / "warmup")
    assert manifest is not None
    return manifest.metrics


def every_stage(action: str, submission: Submission, subjects: Sequence[str]) -> list[str]:
    """The (subject, stage) pairs whose decision in ``submission`` was not ``action``; [] when all were."""
    seen = submission.decisions()
    return [
        f"{subject}/{stage.name}"
        for subject in subjects
        for stage in REGISTRY
        if not any(k[0] == subject and k[2] == stage.name and k[3] == action for k in seen)
    ]


def computed_once(submission: Submission, subject: str, stages: Sequence[str]) -> dict[str, Counter[str]]:
    """Stages among ``stages`` that the jobs of ``submission`` did not compute exactly once, with the
    actions counted; {} when each was computed by one job and found by the others."""
    actions: dict[str, Counter[str]] = {stage: Counter() for stage in stages}
    for (subj, _method, stage, action), n in submission.decisions().items():
        if subj == subject and stage in actions:
            actions[stage][action] += n
    return {stage: counted for stage, counted in actions.items() if counted["run"] != 1}


def table(rows: Sequence[tuple[str, ...]], header: tuple[str, ...]) -> str:
    """A Markdown table for the test's printed summary."""
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


@dataclass
class ResumeStory:
    """The three submissions of :func:`subjects_stopped_resumed_cached`."""

    victim: str  # the subject whose job was stopped mid warm-up
    stopped: str  # what was done to it (the launcher's words: a job id, a process id)
    first: Submission
    second: Submission
    third: Submission


def subjects_stopped_resumed_cached(cluster: Cluster, out: Path, wait_idle: Callable[[], None]) -> ResumeStory:
    """Submit every subject of :data:`SUBJECTS`; stop the batch's first job in its warm-up, the scheduler's way:
    the other job runs to its end and the batch reports the failure; resubmit: the stopped job resumes from its
    checkpoint and both DAGs complete with whole manifests; submit again: every stage is cached. ``wait_idle``
    waits until the cluster runs no job."""
    sweep = [f"subject={','.join(SUBJECTS)}", EARLY_CHECKPOINT, LONG_WARMUP]
    victim, other = SUBJECTS
    started = time.monotonic()
    proc = start(cluster, out, sweep)
    stopped = stop_mid_warmup(cluster, out, victim)
    first = finish(cluster, out, proc, started)
    wait_idle()
    assert first.returncode != 0, "the launcher must report the stopped job"
    assert not (out / victim / "methods" / "interactavatar" / "warmup" / "_manifest.json").exists()
    # The first job failing did not end the batch's other job (Ray's launcher used to give up at once, and
    # Ray ended the tasks still running with their driver).
    assert whole_manifests(out, other) == [], first.driver_output[-3000:]
    assert list((out / victim / ".scratch").glob("warmup*/warmup.pt")), "the checkpoint must survive the stop"

    second = submit(cluster, out, sweep)
    assert second.returncode == 0, second.driver_output[-3000:] + second.job_output[-3000:]
    for subject in SUBJECTS:
        assert whole_manifests(out, subject) == []
    resumed = warmup_metrics(out, victim)["resumed_from_step"]
    assert isinstance(resumed, int) and resumed >= 10, resumed  # EARLY_CHECKPOINT
    assert "resumed from a checkpoint after step" in second.job_output
    assert (victim, "interactavatar", "warmup", "run") in second.decisions()

    third = submit(cluster, out, sweep)
    assert third.returncode == 0, third.driver_output[-3000:]
    assert every_stage("cached", third, SUBJECTS) == [], third.job_output[-3000:]
    return ResumeStory(victim, stopped, first, second, third)


SHARED_BY_METHODS = ("capture", "frames", "keypoints", "fit", "scene", "pbd", "warmup")


def methods_share_stages(cluster: Cluster, out: Path) -> Submission:
    """Fan out over two methods whose stages up to the warm-up are the same (``no_patch`` differs from the
    full model only after it): each of those stages is computed by one job and found by the other."""
    sub = submit(cluster, out, ["method=interactavatar,no_patch"], "subject=synth_a", "run.until=warmup")
    assert sub.returncode == 0, sub.driver_output[-3000:] + sub.job_output[-3000:]
    assert computed_once(sub, "synth_a", SHARED_BY_METHODS) == {}, sub.job_output[-3000:]
    return sub


def summary(title: str, submissions: dict[str, Submission]) -> str:
    """Lines for the test's printed summary: per submission, exit status, wall time, decisions counted."""
    lines = [f"\n## {title}\n"]
    for name, sub in submissions.items():
        actions: Counter[str] = Counter()
        for (_subject, _method, _stage, action), n in sub.decisions().items():
            actions[action] += n
        lines.append(f"- {name}: exit {sub.returncode}, {sub.wall_s:.0f} s wall, stage decisions {dict(actions)}")
    return "\n".join(lines)
