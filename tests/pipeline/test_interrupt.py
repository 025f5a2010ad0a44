"""Ctrl-C (SIGINT) during a run: one line saying what was kept and how to go on, exit status 130, no traceback,
nothing half written, and the previous artifact of the interrupted stage kept."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import REPO, TOY_OVERRIDES, cli_command, cli_env, default_sigint, run_cli, wait_for

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_ctrl_c_during_a_stage_is_one_line_and_keeps_the_previous_artifact(tmp_path) -> None:
    out = tmp_path / "out"
    assert run_cli(*TOY, f"paths.outputs={out}").returncode == 0
    before = (out / "synth_a" / "b" / "b.txt").read_text()
    args = [*TOY, f"paths.outputs={out}", "run.force=true", "run.only=b", "++stage.b.sleep_s=60"]
    lines = _interrupted(args, lambda pid: any((out / "synth_a" / ".tmp").glob("b-*/parts/half.txt")))
    assert len(lines) == 1, lines
    assert "interrupted during stage 'b'" in lines[0]
    assert "its previous artifact, if any, is kept" in lines[0]
    assert "the same command starts it over" in lines[0]
    assert (out / "synth_a" / "b" / "b.txt").read_text() == before
    assert not list((out / "synth_a" / ".tmp").iterdir()), "half-written stage left in .tmp"
    again = run_cli(*TOY, f"paths.outputs={out}")
    assert again.returncode == 0 and "b          cached" in again.stdout, again.stdout


def test_ctrl_c_while_waiting_for_a_lock_is_one_line(tmp_path) -> None:
    """Interrupted outside any stage's computation (here: waiting for another run's lock)."""
    from pipeline.locks import flock

    out = tmp_path / "out"
    assert run_cli(*TOY, f"paths.outputs={out}").returncode == 0
    lock = out / "synth_a" / ".locks" / "a.lock"
    with flock(lock, shared=True, timeout_s=0.0, what="a reader of stage a"):
        lines = _interrupted(
            [*TOY, f"paths.outputs={out}", "run.only=a", "run.force=true"], lambda pid: _has_open(pid, lock)
        )
    assert lines == [
        "interactavatar: interrupted: the stages finished so far are kept and none was left half written; the same "
        "command goes on from there"
    ]


#: ``python -c CTRL_C_ON_IMPORT <module> <args>``: the ``interactavatar`` command with ``args``, sent SIGINT by itself
#: the moment Python starts importing ``module``
CTRL_C_ON_IMPORT = """\
import importlib.abc, os, runpy, signal, sys
class CtrlC(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == TRIGGER:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None
TRIGGER, sys.argv = sys.argv[1], ["interactavatar", *sys.argv[2:]]
sys.meta_path.insert(0, CtrlC())
runpy.run_module("pipeline.launch", run_name="__main__")
"""


@pytest.mark.parametrize("importing", ["hydra", "torch", "pipeline.runner"])
def test_ctrl_c_while_python_imports_the_app_is_one_line(tmp_path, importing: str) -> None:
    """Ctrl-C in the command's first second, while Python still imports Hydra, torch and the pipeline (before any of
    the app's own handling exists): the same one line and status, no traceback of the module that was loading. The
    signal comes from the import of ``importing``, so the moment does not depend on the machine's speed."""
    done = subprocess.run(
        [sys.executable, "-c", CTRL_C_ON_IMPORT, importing, *TOY, f"paths.outputs={tmp_path / 'out'}"],
        cwd=REPO,
        env=cli_env(),
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=default_sigint,
    )
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines() == [
        "interactavatar: interrupted: the stages finished so far are kept and none was left half written; the same "
        "command goes on from there"
    ]


def _has_open(pid: int, path: Path) -> bool:
    """Whether process ``pid`` has ``path`` open (Linux: its /proc/<pid>/fd links)."""
    fds = Path(f"/proc/{pid}/fd")
    try:
        return any(os.readlink(fd) == str(path) for fd in fds.iterdir())
    except OSError:  # a descriptor closed while listing
        return False


def _interrupted(args: list[str], ready: Callable[[int], bool]) -> list[str]:
    """The non-empty lines a CLI run with ``args`` writes to stderr when it gets SIGINT once ``ready(pid)`` holds;
    asserts that it exits with 130 and prints no traceback."""
    proc = subprocess.Popen(
        cli_command(*args),
        cwd=REPO,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    try:
        wait_for(lambda: ready(proc.pid))
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    return [line for line in stderr.splitlines() if line.strip()]


def test_ctrl_c_while_hydra_composes_the_config_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C before the run starts, while Hydra reads the command line and composes the config (it raises
    KeyboardInterrupt out of the app, outside the run's own handling): the same one line and status, no traceback."""
    from pipeline import cli, exit_status

    def composing() -> None:
        raise KeyboardInterrupt

    def process_exit(status: int) -> None:  # os._exit, which would end the suite's own process
        raise SystemExit(status)

    monkeypatch.setattr(cli, "app", composing)
    monkeypatch.setattr(exit_status.os, "_exit", process_exit)
    with pytest.raises(SystemExit) as caught:
        cli.main()
    assert caught.value.code == cli.INTERRUPTED_STATUS == 130
    assert capsys.readouterr().err.splitlines() == [f"interactavatar: {cli.INTERRUPTED_BETWEEN_STAGES}"]
