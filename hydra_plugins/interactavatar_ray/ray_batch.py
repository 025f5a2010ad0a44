"""``hydra/launcher=ray_cluster``: hydra-ray-launcher's launcher, except that a batch collects every job
before it reports a failure.

hydra-ray-launcher 1.2.2 collects its jobs in order with ``ray.get`` and raises at the first that failed; the
driver then exits and Ray ends every task of the batch still running with it. A job whose worker was lost
(a preempted node, an out-of-memory kill) therefore took the whole batch down when it came first. Here every
job runs to its end; the jobs that were lost are named afterwards, in one error, as SLURM's launcher
leaves the other jobs of a batch running. Jobs that raised (a stage failed) come back as failed job
returns, as before, and Hydra reports the first of them.

Defined only where the ``ray`` extra is installed (``.venv-ray``): elsewhere the module defines no launcher,
so Hydra's plugin scan finds nothing to import here.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, configure_log, filter_overrides, setup_globals
from omegaconf import open_dict

try:
    import ray

    from hydra_plugins.hydra_ray_launcher._launcher_util import launch_job_on_ray, start_ray
    from hydra_plugins.hydra_ray_launcher.ray_launcher import RayLauncher
except ImportError:  # the `ray` extra is not installed in this environment
    RayLauncher = None

log = logging.getLogger(__name__)


class LostJobs(RuntimeError):
    """Jobs of a batch whose Ray worker was lost; the batch's other jobs ran to their end."""


if RayLauncher is not None:

    class RayBatchLauncher(RayLauncher):
        """hydra-ray-launcher's ``RayLauncher`` that waits for every job of a batch before it fails."""

        def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
            """Submit one Ray task per job, wait for all of them, then return their results or raise
            :class:`LostJobs` naming every job whose worker was lost."""
            assert self.config is not None and self.hydra_context is not None
            setup_globals()
            configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
            Path(str(self.config.hydra.sweep.dir)).mkdir(parents=True, exist_ok=True)
            log.info(f"Ray launcher: {len(job_overrides)} jobs, sweep output dir {self.config.hydra.sweep.dir}")
            start_ray(self.ray_cfg.init)
            runs = []
            for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
                described = " ".join(filter_overrides(overrides))
                log.info(f"\t#{idx} : {described}")
                sweep_config = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
                with open_dict(sweep_config):
                    # the scheduler's job id is not known in the driver: a stand-in, as hydra-ray-launcher does
                    sweep_config.hydra.job.id = f"job_id_for_{idx}"
                    sweep_config.hydra.job.num = idx
                runs.append(
                    (
                        idx,
                        described,
                        launch_job_on_ray(
                            self.hydra_context,
                            self.ray_cfg.remote,
                            sweep_config,
                            self.task_function,
                            Singleton.get_state(),
                        ),
                    )
                )
            returns, lost = [], []
            for idx, described, run in runs:  # every job, also after one was lost
                try:
                    returns.append(ray.get(run))
                except ray.exceptions.RayError as exc:
                    first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                    lost.append(f"#{idx} ({described}): {type(exc).__name__}: {first_line}")
            if lost:
                raise LostJobs(
                    f"{len(lost)} of {len(runs)} jobs lost their Ray worker; the others ran to their "
                    f"end. Submit the batch again: finished stages are cached and the training "
                    f"stages resume from their checkpoints.\n  " + "\n  ".join(lost)
                )
            return returns
