"""Checks a batch makes in the Hydra driver before it submits any job (a Hydra callback, ``hydra.callbacks``).

A problem found here ends the driver with one line per problem naming the fix (exit status 2) and nothing
submitted: the cluster's (SLURM accounting), and every job's config, checked as the job would check it.
"""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
from collections.abc import Callable
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
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


def sweep_jobs(config: DictConfig) -> list[list[str]]:
    """Each job's overrides, as Hydra's basic sweeper will expand ``hydra.sweeper.params`` and the command line's
    overrides of the multirun whose driver's config is ``config``; none for another sweeper, whose jobs are
    not known before it runs (an optimiser's)."""
    target = str(OmegaConf.select(config, "hydra.sweeper._target_", default="") or "")
    if not target.endswith(f".{BasicSweeper.__name__}"):
        return []
    params = OmegaConf.select(config, "hydra.sweeper.params", default=None) or {}
    arguments = [*(f"{key}={value}" for key, value in params.items()), *config.hydra.overrides.task]
    parser = OverridesParser.create(config_loader=GlobalHydra.instance().config_loader())
    return [job for batch in BasicSweeper.split_arguments(parser.parse_overrides(arguments), None) for job in batch]


def job_config(config: DictConfig, overrides: list[str]) -> DictConfig:
    """The config a job of the multirun whose driver's config is ``config`` runs with: composed as its launcher
    composes it, less the ``hydra`` node, with ``run.overrides`` set: as the app receives and completes it."""
    job = copy.deepcopy(GlobalHydra.instance().config_loader().load_sweep_config(config, overrides))
    with read_write(job), open_dict(job):
        job.run.overrides = list(job.hydra.overrides.task)  # as the app records them
        del job["hydra"]
    return job


def job_problems(config: DictConfig, overrides: list[str]) -> list[str]:
    """What the job with ``overrides`` would refuse to run with (:func:`pipeline.config.validate_config`)."""
    try:
        job = job_config(config, overrides)
        validate_config(job, load_registry(job.pipeline.stages_module))
    except ConfigError as exc:
        return list(exc.problems)
    except HydraException as exc:  # an override the job's config has no key or option for
        return [composition_problem(exc, overrides, lambda: setting_paths(config))]
    except RegistryError as exc:
        return [str(exc)]
    return []


def batch_problems(config: DictConfig) -> list[str]:
    """One line per job of the multirun (:func:`sweep_jobs`) that could not run, naming the overrides that set it
    apart from the other jobs and every problem of its config."""
    jobs = sweep_jobs(config)
    shared = set.intersection(*(set(job) for job in jobs)) if jobs else set()
    lines = []
    for number, overrides in enumerate(jobs):
        problems = job_problems(config, overrides)
        if problems:
            own = " ".join(o for o in overrides if o not in shared)
            lines.append(f"job {number}{f' ({own})' if own else ''}: {'; '.join(problems)}")
    return lines


class BatchPreflight(Callback):
    """Refuses a batch the cluster cannot carry out (:func:`slurm_accounting_problem`), or one of whose jobs
    could not run (:func:`batch_problems`), before any job is submitted."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        problem = slurm_accounting_problem(config)
        if problem is not None:
            _refuse(problem)
        HydraConfig.instance().set_config(config)  # the jobs' checks read it (hydra.searchpath: the user's methods)
        problems = batch_problems(config)
        if problems:
            listed = "\n  - ".join(problems)
            _refuse(f"the batch was not started, {len(problems)} of its jobs cannot run:\n  - {listed}")


def _refuse(message: str) -> None:
    print(f"interactavatar: error: {message}", file=sys.stderr)
    sys.exit(2)  # SystemExit: Hydra turns a callback's exceptions into warnings, but not this
