"""Checks a batch makes in the Hydra driver before it submits any job (a Hydra callback, ``hydra.callbacks``).

A problem found here ends the driver with one line naming the fix (exit status 2) and nothing submitted.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

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


class BatchPreflight(Callback):
    """Refuses a batch the cluster cannot carry out (:func:`slurm_accounting_problem`) before any job is
    submitted."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        problem = slurm_accounting_problem(config)
        if problem is not None:
            print(f"interactavatar: error: {problem}", file=sys.stderr)
            sys.exit(2)  # SystemExit: Hydra turns a callback's exceptions into warnings, but not this
