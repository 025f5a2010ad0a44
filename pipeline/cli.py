"""The ``interactavatar`` Hydra app: one whole DAG for one subject per job.

Single run::

    interactavatar subject=synth_a quality=draft run.until=frames

Batch (one job per subject, through any Hydra launcher)::

    interactavatar -m subject=synth_a,synth_b hydra/launcher=local
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import shutil
import sys
import tempfile
import traceback
from collections.abc import Sequence
from pathlib import Path

import hydra
from hydra import compose, initialize_config_dir
from hydra._internal.utils import get_args_parser
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import ConfigCompositionException, HydraException, OverrideParseException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from pipeline.batch import JobFailed, one_line
from pipeline.config import CONF_DIR, ConfigError, fix_command, validate_config
from pipeline.exit_status import INTERRUPTED_BETWEEN_STAGES, INTERRUPTED_STATUS, exit_interrupted_before_the_run
from pipeline.overrides import composition_problem, override_key, setting_paths
from pipeline.registry import RegistryError, StageRegistry, load_registry
from pipeline.runner import Interrupted, MissingUpstream, Runner, StageFailed, StageReport
from pipeline.summary import metrics_table, stage_table
from pipeline.threads import use_threads
from pipeline.workspace import LockTimeout, outputs_problem, run_overrides

USER_ERRORS = (ConfigError, RegistryError, MissingUpstream, StageFailed, LockTimeout)


def hydra_root(outputs: str) -> str:
    """Where Hydra keeps its logs (``hydra.run.dir``, ``hydra.sweep.dir``): ``<paths.outputs>/_hydra``, or a
    temporary folder when ``paths.outputs`` is empty or cannot be written, so that the run stops with one clear
    error about ``paths.outputs`` (from :func:`run_app`'s config check) instead of Hydra's traceback, or when its
    disk is all but full, so that a run that finds every stage cached (and writes nothing else) still runs, and
    one that must compute stops with the stage's one line naming the file it could not write."""
    if outputs_problem(outputs) is None and _free_bytes(Path(outputs)) >= HYDRA_LOG_MIN_FREE_BYTES:
        return str(Path(outputs) / "_hydra")
    return str(Path(tempfile.gettempdir()) / "interactavatar-hydra")


#: Free bytes on the outputs' disk below which Hydra's logs (a few kB a run) go to the temporary folder.
HYDRA_LOG_MIN_FREE_BYTES = 1 << 20


def _free_bytes(path: Path) -> int:
    """Free bytes on the disk of ``path``, or of its nearest folder that exists."""
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


OmegaConf.register_new_resolver("hydra_root", hydra_root, replace=True)


def run_app(cfg: DictConfig, job: bool = False) -> list[StageReport]:
    """Validate ``cfg``, then plan (``run.dry``) or run the DAG and print the summary. ``job``: the run is a job of
    its own process (the command's, a batch's), which computes on ``run.threads``
    (:func:`pipeline.threads.use_threads`); a caller in its own process (a test, a benchmark) keeps its thread
    count."""
    registry = load_registry(cfg.pipeline.stages_module)
    cfg = validate_config(cfg, registry)
    if job and not cfg.run.dry:
        use_threads(cfg.run.threads)
    runner = Runner(cfg, registry)
    if cfg.run.dry:
        reports = runner.plan()
        print(f"dry run for subject '{cfg.subject}': nothing was executed")
        return reports
    reports = runner.run()
    print()
    print(stage_table(reports))
    print()
    print(metrics_table(reports))
    for line in comparison_fixes(cfg, reports):
        print(line)
    results = result_lines(runner, registry)
    if results:
        print()
        print("\n".join(results))
    return reports


def result_lines(runner: Runner, registry: StageRegistry) -> list[str]:
    """Where to look once a run is done: the report's path, and the browser viewer's page with the command that
    serves it (those the run's stages wrote)."""
    lines = []
    report_html = runner.artifact_dir("report") / "report.html" if "report" in registry else None
    if report_html is not None and report_html.is_file():
        lines.append(f"report: {report_html.resolve()}")
    viewer_page = runner.artifact_dir("viewer") / "index.html" if "viewer" in registry else None
    if viewer_page is not None and viewer_page.is_file():
        lines.append(f"viewer: {viewer_page.resolve()}")
        lines.append(f"        or serve it: interactavatar-view {shlex.quote(str(runner.ws.root.resolve()))}")
    return lines


def comparison_fixes(cfg: DictConfig, reports: list[StageReport]) -> list[str]:
    """One line per training run the comparison left out (stale, corrupted), with the command that recomputes
    it in this DAG: this command line's overrides repeated (:func:`pipeline.config.fix_command`)."""
    metrics = next((r.metrics for r in reports if r.stage == "compare"), {})
    lines = []
    for key, kind in (("methods_stale", "stale"), ("methods_corrupt", "corrupted")):
        value = str(metrics.get(key, "-"))
        for run in [] if value == "-" else value.split(","):
            lines.append(
                f"comparison: {run} left out ({kind}); recompute it with "
                f"`{fix_command(cfg, *run_overrides(run), 'run.until=evaluate')}`, then "
                f"`{fix_command(cfg, 'run.only=compare')}`"
            )
    return lines


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def app(cfg: DictConfig) -> None:
    """The Hydra app: one job, the DAG for one subject (:func:`run_app`), its errors in one message each."""
    OmegaConf.update(cfg, "run.overrides", list(HydraConfig.get().overrides.task))  # fix commands repeat them
    batch = HydraConfig.get().mode == RunMode.MULTIRUN
    try:
        run_app(cfg, job=True)
    except USER_ERRORS as exc:
        print(f"interactavatar: error: {exc}", file=sys.stderr)
        if batch:  # the launcher records this job as failed and goes on with the others; the batch names it
            raise JobFailed(one_line(exc)) from None
        sys.exit(2 if isinstance(exc, (ConfigError, RegistryError)) else 1)
    except (Interrupted, KeyboardInterrupt) as exc:  # Ctrl-C: say what was kept, not where Python was
        said = str(exc) if isinstance(exc, Interrupted) else INTERRUPTED_BETWEEN_STAGES
        print(f"interactavatar: {said}", file=sys.stderr)
        sys.exit(INTERRUPTED_STATUS)
    except Exception as exc:
        if not batch:
            raise
        traceback.print_exc()  # a fault of the app's: in full in the job's own output, in one line at the batch's end
        raise JobFailed(f"{type(exc).__name__}: {one_line(exc)}") from None


#: Hydra's errors about the command line: an override it cannot apply, a group option that does not exist, a
#: malformed override.
COMMAND_LINE_ERRORS = (ConfigCompositionException, OverrideParseException)
#: Set to 1 by the user: Hydra's own report of its errors, with the stack trace.
FULL_ERROR = "HYDRA_FULL_ERROR"


def main() -> None:
    """Console entry point (``interactavatar``): :func:`app`, with Hydra's errors about the command line in one
    line naming the override and the key it most likely meant (:func:`pipeline.overrides.composition_problem`), exit
    status 2, before anything is written."""
    previous = os.environ.get(FULL_ERROR)
    if previous == "1":
        _app_quiet_on_ctrl_c()
        return
    os.environ[FULL_ERROR] = "1"  # Hydra raises its errors to here, instead of printing them with a stack trace
    try:
        _app_quiet_on_ctrl_c()
    except COMMAND_LINE_ERRORS as exc:
        overrides = hydra_args().overrides
        problem = composition_problem(exc, overrides, lambda: setting_paths(compose_for_keys(overrides)))
        print(f"interactavatar: error: {problem}", file=sys.stderr)
        sys.exit(2)
    finally:
        if previous is None:
            del os.environ[FULL_ERROR]
        else:
            os.environ[FULL_ERROR] = previous


def _app_quiet_on_ctrl_c() -> None:
    """:func:`app`, where a Ctrl-C before the run starts (Hydra reading the command line and composing the config, a
    second or so) ends as one between stages does: one line, exit status 130, no traceback."""
    try:
        app()
    except KeyboardInterrupt:
        exit_interrupted_before_the_run()


def hydra_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line as Hydra's own parser reads it (``overrides``, ``multirun``, ...)."""
    return get_args_parser().parse_args(sys.argv[1:] if argv is None else argv)


def compose_for_keys(overrides: Sequence[str]) -> DictConfig:
    """The app's config as far as it composes with ``overrides``, to name its keys: with every override that is no
    sweep and composes (the groups chosen, ``hydra.searchpath``), else with the groups chosen alone, else the
    defaults."""
    parsed = []
    with contextlib.suppress(HydraException):
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    single = [o.input_line for o in parsed if not o.is_sweep_override() and o.input_line is not None]
    groups = [o for o in single if "." not in override_key(o) or o.startswith("hydra.")]
    GlobalHydra.instance().clear()
    for tried in (single, groups, []):
        with contextlib.suppress(HydraException), initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            return compose(config_name="config", overrides=tried)
    return OmegaConf.create()


if __name__ == "__main__":
    main()
