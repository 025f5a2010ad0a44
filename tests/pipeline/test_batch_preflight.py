"""A SLURM batch on a cluster without job accounting is refused before any job is submitted (issue 36, item
16): submitit follows its jobs with sacct, and without accounting it waited forever on a cancelled job."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

from hydra import compose, initialize_config_dir

from pipeline.batch_checks import slurm_accounting_problem
from tests.conftest import CONF_DIR, REPO, cli_command, cli_env

DISABLED = "Slurm accounting storage is disabled"


def _fake_command(bin_dir: Path, name: str, body: str) -> None:
    path = bin_dir / name
    path.write_text(f"#!/bin/sh\n{body}\n")
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def test_a_slurm_batch_without_accounting_is_refused_before_submitting(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    _fake_command(bin_dir, "sacct", f'echo "{DISABLED}" >&2; exit 1')
    _fake_command(bin_dir, "sbatch", f'touch {tmp_path / "submitted"}; echo "Submitted batch job 1"')
    env = {**cli_env(), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    done = subprocess.run(
        cli_command(
            "-m", "subject=synth_a", "hydra/launcher=slurm", "quality=smoke", f"paths.outputs={tmp_path / 'out'}"
        ),
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    assert "keeps no job accounting" in done.stderr and "slurmdbd" in done.stderr, done.stderr
    assert not (tmp_path / "submitted").exists(), "a job was submitted"


def _cfg(*overrides: str):
    """The composed config with its hydra node, as the driver's callbacks see it."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides), return_hydra_config=True)


def _slurm_cfg():
    return _cfg("hydra/launcher=slurm")


def test_accounting_is_asked_of_sacct_only_for_slurm_batches():
    asked: list[list[str]] = []

    def sacct(args, **kwargs):
        asked.append(args)
        return subprocess.CompletedProcess(args, 0, stdout="", stderr="")

    assert slurm_accounting_problem(_cfg(), run=sacct) is None
    assert asked == []  # the basic launcher: no SLURM, nothing asked


def test_a_slurm_batch_asks_sacct(tmp_path, monkeypatch):
    asked: list[list[str]] = []

    def sacct(args, **kwargs):
        asked.append(args)
        return subprocess.CompletedProcess(args, 0, stdout="", stderr="")

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    _fake_command(bin_dir, "sacct", "exit 0")
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    assert slurm_accounting_problem(_slurm_cfg(), run=sacct) is None
    assert asked and asked[0][0] == "sacct"
    monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))
    missing = slurm_accounting_problem(_slurm_cfg(), run=sacct)
    assert missing is not None and "no `sacct`" in missing


def test_other_sacct_failures_are_named(tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    _fake_command(bin_dir, "sacct", "exit 1")
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    failed = slurm_accounting_problem(
        _slurm_cfg(),
        run=lambda args, **kw: subprocess.CompletedProcess(
            args, 1, stdout="", stderr="sacct: error: Problem talking to the database: Connection refused"
        ),
    )
    assert failed is not None and "Connection refused" in failed and "keeps no job accounting" not in failed
    disabled = slurm_accounting_problem(
        _slurm_cfg(), run=lambda args, **kw: subprocess.CompletedProcess(args, 1, stdout="", stderr=DISABLED)
    )
    assert disabled is not None and "keeps no job accounting" in disabled


def _toy_batch(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess[str]:
    """A local multirun of the toy DAG with per-method stages (``tests.toy_methods``) writing under tmp_path."""
    return subprocess.run(
        cli_command(
            "-m",
            "pipeline.stages_module=tests.toy_methods",
            "stage=[]",
            "+stage.a.value=1",
            "+stage.cmp.methods=[m1]",
            "+stage.cmp.seeds=[0]",
            "method.name=m1",
            "+method.p_value=1",
            "run.progress=false",
            f"paths.outputs={tmp_path / 'out'}",
            *overrides,
        ),
        cwd=REPO,
        env=cli_env(),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_a_batch_with_a_bad_job_is_refused_before_any_job_runs(tmp_path):
    """Issue 52, item 7: with `-m seed=0,-1`, job 0 trained fully before job 1 failed."""
    done = _toy_batch(tmp_path, "seed=0,-1")
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    assert "the batch was not started, 1 of its jobs cannot run" in done.stderr, done.stderr
    assert "\n  - job 1 (seed=-1): seed=-1: use a non-negative integer" in done.stderr, done.stderr
    assert "job 0" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "out").exists(), sorted((tmp_path / "out").rglob("*"))


def test_a_batch_of_good_jobs_runs_them_all(tmp_path):
    done = _toy_batch(tmp_path, "seed=0,1")
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    methods = tmp_path / "out" / "synth_a" / "methods"
    assert sorted(p.name for p in methods.iterdir()) == ["m1", "m1-seed1"]
