"""A batch (``interactavatar -m``, any launcher): every job's config composed once, in the driver, before any job
runs, and handed to the job; the jobs that failed named at the end, one line each.

Hydra's launchers compose a job's config from the config files when the job starts (in the driver, a joblib worker,
a SLURM job), so an edit of ``conf/`` during a batch changed or broke its later jobs. :class:`CheckedSweeper` (the
app's sweeper, ``hydra/sweeper=interactavatar``) composes every job's config before the first job starts, checks each
as the job would (:func:`pipeline.batch_checks.batch_problems`: a batch with a job that cannot run is not started),
keeps them in the batch's folder (``<hydra.sweep.dir>/.jobs/``) and lends the launcher a config loader that reads a
job's config from there (:class:`ComposedConfigs`). The code a job runs is the code installed when it starts.

A launcher that runs several jobs at once on this machine (joblib's ``n_jobs``, submitit's local executor) gets
jobs whose ``run.threads=auto`` is their share of the cores (:func:`share_threads`), so that the jobs' threads
together do not exceed the cores; jobs on other machines (SLURM, Ray) count their own.
"""

from __future__ import annotations

import pickle
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins import basic_sweeper
from hydra.core.config_loader import ConfigLoader
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.plugins.launcher import Launcher
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, RunMode, TaskFunction
from omegaconf import DictConfig, OmegaConf

from pipeline.batch_checks import batch_problems, job_label, refuse
from pipeline.config import ConfigError
from pipeline.threads import AUTO, choose_threads, env_threads, usable_cores

#: The folder of a batch's folder where its jobs' composed configs are kept, one pickle per job.
JOBS_FOLDER = ".jobs"


class JobFailed(RuntimeError):
    """A job of a batch failed; the message is one line. It crosses from the job's process to the driver, so it
    takes one argument, which pickles (the runner's errors take several)."""


def one_line(exc: BaseException) -> str:
    """``exc``'s message as one line: a config's problems joined by ``;``, any other message's line breaks folded."""
    if isinstance(exc, ConfigError):
        return "; ".join(exc.problems)
    return " ".join(str(exc).split())


def failure(exc: BaseException) -> str:
    """What a failed job's error says, in one line: a :class:`JobFailed`'s message, any other error's class and
    message (one the launcher raised for the job)."""
    return one_line(exc) if isinstance(exc, JobFailed) else f"{type(exc).__name__}: {one_line(exc)}"


#: Hydra launchers that run a batch's jobs on this machine, by the end of their ``_target_``
JOBLIB, SUBMITIT_LOCAL, BASIC = "JoblibLauncher", "submitit_launcher.LocalLauncher", "BasicLauncher"


def jobs_at_once(launcher: Any, jobs: int, cores: int) -> int:
    """How many of a batch's ``jobs`` the launcher (``hydra.launcher``) runs at once on this machine of ``cores``
    cores: joblib's ``n_jobs`` (its convention: -1 all cores, -2 all but one), submitit's local executor all of
    them, Hydra's basic launcher one after the other; 0 where they run on other machines (SLURM, Ray, any other)."""
    target = str(OmegaConf.select(launcher, "_target_", default="") if OmegaConf.is_config(launcher) else "")
    if target.endswith(JOBLIB):
        n_jobs = OmegaConf.select(launcher, "n_jobs", default=None)
        n = 1 if n_jobs is None else int(n_jobs)
        return min(jobs, n if n > 0 else max(1, cores + 1 + n))
    if target.endswith(SUBMITIT_LOCAL):
        return jobs
    if target.endswith(BASIC):
        return 1
    return 0


def share_threads(configs: Sequence[DictConfig], launcher: Any) -> int | None:
    """Set ``run.threads`` of each job whose setting is ``auto`` to its share of this machine's cores when the
    launcher runs several of them at once here (:func:`jobs_at_once`); the share, or None where nothing was
    shared."""
    cores = usable_cores()
    at_once = jobs_at_once(launcher, len(configs), cores)
    if at_once < 2:
        return None
    threads = choose_threads(AUTO, cores, env_threads(), jobs=at_once)
    for job in configs:
        if str(OmegaConf.select(job, "run.threads", default=AUTO)) == AUTO:
            OmegaConf.update(job, "run.threads", str(threads), force_add=True)
    return threads


class ComposedConfigs(ConfigLoader):
    """Hydra's config loader, except that the config of a job this batch composed in advance is read from its
    pickle in the batch's folder (whatever the config files say by then); any other is composed as Hydra composes
    it. It crosses to the jobs' processes with the launcher: it holds a folder and file names, not configs."""

    def __init__(self, loader: ConfigLoader) -> None:
        self.loader = loader
        self.folder: Path | None = None
        self.files: dict[tuple[str, ...], str] = {}

    def keep(self, folder: Path, configs: dict[tuple[str, ...], DictConfig]) -> None:
        """Write each job's composed config (by its overrides) to ``folder``, for :meth:`load_sweep_config`."""
        folder.mkdir(parents=True, exist_ok=True)
        for number, (overrides, config) in enumerate(configs.items()):
            name = f"{number}.pickle"
            (folder / name).write_bytes(pickle.dumps(config))
            self.files[overrides] = name
        self.folder = folder

    def load_sweep_config(self, master_config: DictConfig, sweep_overrides: list[str]) -> DictConfig:
        """The job's config as composed before the batch started (Hydra's where this batch did not compose it)."""
        name = self.files.get(tuple(sweep_overrides))
        if name is None or self.folder is None:
            return self.loader.load_sweep_config(master_config, sweep_overrides)
        config = pickle.loads((self.folder / name).read_bytes())
        OmegaConf.copy_cache(from_config=master_config, to_config=config)  # the driver's ${now:...}, as Hydra does
        assert isinstance(config, DictConfig)
        return config

    # the rest of the interface: Hydra's own loader's

    def load_configuration(
        self,
        config_name: str | None,
        overrides: list[str],
        run_mode: RunMode,
        from_shell: bool = True,
        validate_sweep_overrides: bool = True,
    ) -> DictConfig:
        return self.loader.load_configuration(config_name, overrides, run_mode, from_shell, validate_sweep_overrides)

    def get_search_path(self) -> Any:
        return self.loader.get_search_path()

    def get_sources(self) -> Any:
        return self.loader.get_sources()

    def list_groups(self, parent_name: str) -> list[str]:
        return self.loader.list_groups(parent_name)

    def get_group_options(
        self,
        group_name: str,
        results_filter: Any = None,
        config_name: str | None = None,
        overrides: list[str] | None = None,
    ) -> list[str]:
        return self.loader.get_group_options(group_name, results_filter, config_name, overrides)

    def compute_defaults_list(self, config_name: str | None, overrides: list[str], run_mode: RunMode) -> Any:
        return self.loader.compute_defaults_list(config_name, overrides, run_mode)


class FailuresKept:
    """A launcher that hands the sweeper the returns of the jobs that completed and keeps those that failed
    (:attr:`failed`: number, overrides, error), so that the batch goes on and names every failure at its end."""

    def __init__(self, launcher: Launcher) -> None:
        self.launcher = launcher
        self.failed: list[tuple[int, list[str], BaseException]] = []

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> list[JobReturn]:
        returns = self.launcher.launch(job_overrides, initial_job_idx)
        completed = []
        for number, (overrides, job) in enumerate(zip(job_overrides, returns, strict=True), start=initial_job_idx):
            if job.status is JobStatus.FAILED:  # its error is the value (the return_value property prints, raises)
                self.failed.append((number, list(overrides), job._return_value))
            else:
                completed.append(job)
        return completed


class CheckedSweeper(Sweeper):
    """Hydra's basic sweeper (the same jobs, batches and launchers; it runs them) that composes and checks every
    job's config before the first job starts and hands each job its own (module docstring), and ends a batch in which
    jobs failed with one line per failed job and exit status 1, after the others ran to their end.

    It holds a basic sweeper rather than being one: Hydra's plugin scan executes the module of the basic sweeper
    again, and a subclass of the class it replaced would fail in the basic sweeper's own ``__init__``."""

    def __init__(self, max_batch_size: int | None = None, params: dict[str, str] | None = None) -> None:
        super().__init__()
        self.basic = basic_sweeper.BasicSweeper(max_batch_size, params)  # the class as the plugin scan left it

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.composed = ComposedConfigs(hydra_context.config_loader)
        context = HydraContext(config_loader=self.composed, callbacks=hydra_context.callbacks)
        self.basic.setup(hydra_context=context, task_function=task_function, config=config)
        assert self.basic.launcher is not None
        self.failures = FailuresKept(self.basic.launcher)
        self.basic.launcher = self.failures  # type: ignore[assignment]  # it launches as the launcher does

    def sweep(self, arguments: list[str]) -> Any:
        config = self.config
        assert config is not None, "setup first"
        parsed = OverridesParser.create(config_loader=self.composed).parse_overrides(
            self.basic._parse_config() + arguments  # the basic sweeper's params first, as its sweep takes them
        )
        jobs = [job for batch in self.basic.split_arguments(parsed, None) for job in batch]
        HydraConfig.instance().set_config(config)  # the jobs' checks read it (hydra.searchpath: user methods)
        configs, problems = batch_problems(config, jobs, self.composed.loader.load_sweep_config)
        if problems:
            listed = "\n  - ".join(problems)
            refuse(f"the batch was not started, {len(problems)} of its jobs cannot run:\n  - {listed}")
        share_threads(list(configs.values()), config.hydra.launcher)
        self.composed.keep(Path(str(config.hydra.sweep.dir)) / JOBS_FOLDER, configs)
        returns = self.basic.sweep(arguments)
        if self.failures.failed:
            lines = [f"{job_label(n, overrides, jobs)}: {failure(exc)}" for n, overrides, exc in self.failures.failed]
            listed = "\n  - ".join(lines)
            print(
                f"interactavatar: error: {len(lines)} of {len(jobs)} jobs failed (the others ran to their end):\n"
                f"  - {listed}",
                file=sys.stderr,
            )
            sys.exit(1)
        return returns
