"""A batch (``interactavatar -m``) composes every job's config once, in the driver, before any job runs, and hands
each job its own; a job that fails is named at the end in one line, the others run to their end.

Hydra's launchers composed each job's config from ``conf/`` when the job started, so an edit of ``conf/`` during a
batch changed or broke its later jobs; and a job that failed ended the batch in Hydra's stack trace."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import CONF_DIR, REPO, TOY_OVERRIDES, cli_command, cli_env, run_cli, wait_for

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_an_edit_of_conf_during_a_batch_changes_none_of_its_jobs(tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    out, trace = tmp_path / "out", tmp_path / "trace.txt"
    batch = subprocess.Popen(
        cli_command(
            "--config-path",
            str(conf),  # the copy instead of conf/
            "-m",
            "subject=s1,s2",
            *TOY,
            f"paths.outputs={out}",
            f"++stage.a.trace={trace}",
            "++stage.b.sleep_s=2",  # the first job is still running when conf/ is edited
        ),
        cwd=REPO,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: trace.exists() and " end " in trace.read_text(), timeout_s=120)  # the first job's stage a
        with open(conf / "config.yaml", "a") as config:
            config.write("run: [\n")  # no longer YAML
        stdout, stderr = batch.communicate(timeout=300)
    finally:
        batch.kill()
    assert batch.returncode == 0, stdout[-2000:] + stderr[-2000:]
    for subject in ("s1", "s2"):
        assert (out / subject / "c" / "c.txt").read_text() == "a=1\nb=1\nc=1\n"
    assert trace.read_text().count(" end ") == 2


@pytest.mark.parametrize("launcher", [[], ["hydra/launcher=local"]])
def test_a_batch_names_each_failed_job_in_one_line_and_runs_the_others(tmp_path: Path, launcher: list[str]) -> None:
    out = tmp_path / "out"
    done = run_cli("-m", *launcher, "subject=s1,s2,s3", "++stage.c.fail=false,true", *TOY, f"paths.outputs={out}")
    assert done.returncode == 1, done.stdout[-2000:] + done.stderr[-2000:]
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    failed = "stage 'c' failed: RuntimeError: toy stage c was told to fail; nothing was written to"
    assert lines[-4] == "interactavatar: error: 3 of 6 jobs failed (the others ran to their end):", lines
    for line, (number, subject) in zip(lines[-3:], ((1, "s1"), (3, "s2"), (5, "s3")), strict=True):
        assert line.startswith(f"  - job {number} (subject={subject} ++stage.c.fail=True): {failed}"), lines
    for subject in ("s1", "s2", "s3"):
        assert (out / subject / "c" / "c.txt").exists()  # each subject's good job ran; its failing one kept it
