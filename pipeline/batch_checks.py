"""Checks a batch makes in the Hydra driver before it submits any job.

A problem found here ends the driver with one line per problem naming the fix (exit status 2) and nothing
submitted: the cluster's (SLURM accounting, a Hydra callback), and every job's config, checked as the job would check
it (by the batch's sweeper, :mod:`pipeline.batch`, with the configs it hands the jobs).
"""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any

from hydra.errors import HydraException
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from pipeline.config import ConfigError, validate_config
from pipeline.overrides import composition_problem, setting_paths
from pipeline.registry import RegistryError, load_registry

#: how a launcher config's ``_target_`` ends for a launcher that submits through SLURM (submitit)
SLURM_LAUNCHER = "SlurmLauncher"


def slurm_accounting_problem(
    config: DictConfig, run: Callable[..., subprocess.CompletedProcess[str]] = subprocess.run
) -> str | None:
    """Why a SLURM batch would never finish on this cluster, or ``None``.

    submitit learns its jobs' states only from ``sacct``; where SLURM keeps no accounting, ``sacct`` fails, a
    cancelled or failed job is never seen to end, and the driver waits forever. ``run`` runs a command (tests
    pass a fake)."""
    target = str(OmegaConf.select(config, "hydra.launcher._target_", default="") or "")
    if not target.endswith(SLURM_LAUNCHER):
        return None
    if shutil.which("sacct") is None:
        return (
            "hydra/launcher=slurm: no `sacct` on this machine's PATH. submitit follows the batch's jobs "
            "with sacct: start the batch where SLURM's client commands are installed (a login node)"
        )
    done = run(
        ["sacct", "--noheader", "--allocations", "--starttime", "now", "--format", "JobID"],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    if done.returncode == 0:
        return None
    said = " ".join((done.stderr or done.stdout or "").split())
    if "disabled" in said.lower():
        return (
            f"hydra/launcher=slurm: this cluster keeps no job accounting (sacct: {said}). submitit learns "
            f"its jobs' states from sacct, so a cancelled job would never be seen to end and the batch "
            f"would wait forever. Ask for accounting (slurmdbd, AccountingStorageType=accounting_storage/"
            f"slurmdbd in slurm.conf), or submit one job per subject with sbatch yourself"
        )
    return f"hydra/launcher=slurm: `sacct` failed ({said or f'exit status {done.returncode}'}); submitit needs it"


#: Composes the config of a job of a multirun: (the driver's config, the job's overrides) -> the job's config with its
#: ``hydra`` node (Hydra's ``ConfigLoader.load_sweep_config``).
Composer = Callable[[DictConfig, list[str]], DictConfig]


def job_config(job: DictConfig) -> DictConfig:
    """The config the app runs a job of a multirun with, from the job's composed config ``job`` (its ``hydra`` node
    included): a copy without the ``hydra`` node, with ``run.overrides`` set as the app sets them."""
    job = copy.deepcopy(job)
    with read_write(job), open_dict(job):
        job.run.overrides = list(job.hydra.overrides.task)
        del job["hydra"]
    return job


def job_problems(config: DictConfig, overrides: list[str], compose: Composer) -> tuple[DictConfig | None, list[str]]:
    """The composed config of the job with ``overrides`` of the multirun whose driver's config is ``config``, and
    what the job would refuse to run with (:func:`pipeline.config.validate_config`): (None, its problems) where it
    has any."""
    try:
        job = compose(config, overrides)
        app = job_config(job)
        validate_config(app, load_registry(app.pipeline.stages_module))
    except ConfigError as exc:
        return None, list(exc.problems)
    except HydraException as exc:  # an override the job's config has no key or option for
        return None, [composition_problem(exc, overrides, lambda: setting_paths(config))]
    except RegistryError as exc:
        return None, [str(exc)]
    return job, []


def job_label(number: int, overrides: Sequence[str], jobs: Sequence[Sequence[str]]) -> str:
    """``job <number> (<the overrides that set it apart from the other jobs of jobs>)``."""
    shared = set.intersection(*(set(job) for job in jobs)) if jobs else set()
    own = " ".join(o for o in overrides if o not in shared)
    return f"job {number}{f' ({own})' if own else ''}"


def batch_problems(
    config: DictConfig, jobs: Sequence[list[str]], compose: Composer
) -> tuple[dict[tuple[str, ...], DictConfig], list[str]]:
    """Each job of the multirun whose driver's config is ``config`` (``jobs``: their overrides) composed once, by its
    overrides, and one line per job that could not run, naming it (:func:`job_label`) and every problem of its
    config."""
    configs, lines = {}, []
    for number, overrides in enumerate(jobs):
        job, problems = job_problems(config, overrides, compose)
        if job is not None:
            configs[tuple(overrides)] = job
        else:
            lines.append(f"{job_label(number, overrides, jobs)}: {'; '.join(problems)}")
    return configs, lines


class BatchPreflight(Callback):
    """Refuses a batch the cluster cannot carry out (:func:`slurm_accounting_problem`) before any job is submitted
    (the jobs' own configs are checked by the batch's sweeper, :class:`pipeline.batch.CheckedSweeper`)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        problem = slurm_accounting_problem(config)
        if problem is not None:
            refuse(problem)


def refuse(message: str) -> None:
    """End the driver of a batch with ``message``, exit status 2, before any job is submitted."""
    print(f"interactavatar: error: {message}", file=sys.stderr)
    sys.exit(2)  # SystemExit: Hydra turns a callback's exceptions into warnings, but not this
