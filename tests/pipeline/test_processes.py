"""The runner across real processes: SIGKILL mid-stage, concurrent runs, CLI errors, multirun."""

from __future__ import annotations

import json
import signal
import subprocess

from pipeline.locks import flock
from tests.conftest import REPO, TOY_OVERRIDES, cli_command, cli_env, run_cli, wait_for

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_sigkill_mid_stage_leaves_nothing_that_looks_complete(tmp_path):
    out = tmp_path / "out"
    args = [*TOY, f"paths.outputs={out}", "++stage.a.sleep_s=60"]
    proc = subprocess.Popen(
        cli_command(*args), cwd=REPO, env=cli_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        # Wait until stage a has written half of its output into its temporary dir.
        wait_for(lambda: any((out / "synth_a" / ".tmp").glob("a-*/parts/half.txt")))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    assert not (out / "synth_a" / "a").exists()
    result = run_cli(*TOY, f"paths.outputs={out}")
    assert result.returncode == 0, result.stderr
    assert "a          run       outputs missing" in result.stdout
    assert not list((out / "synth_a" / ".tmp").iterdir()), "stale temporary dir not cleaned"
    assert (out / "synth_a" / "c" / "c.txt").read_text() == "a=1\nb=1\nc=1\n"


def test_two_concurrent_runs_do_not_interleave(tmp_path):
    out, trace = tmp_path / "out", tmp_path / "trace.log"
    args = [*TOY, f"paths.outputs={out}", "++stage.a.sleep_s=1.5"] + [f"++stage.{s}.trace={trace}" for s in "abcd"]
    procs = [
        subprocess.Popen(
            cli_command(*args), cwd=REPO, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1] for o in outs]
    events = [line.split() for line in trace.read_text().splitlines()]
    # Each stage was computed exactly once; the other run found it cached under the lock.
    for s in "abcd":
        assert [e[1] for e in events if e[0] == s] == ["start", "end"], events
    assert sum("a          cached" in o[0] for o in outs) == 1
    # Both runs agree on the final artifacts.
    manifest = json.loads((out / "synth_a" / "c" / "_manifest.json").read_text())
    assert manifest["outputs"]


def test_a_cached_stage_does_not_wait_for_a_run_that_reads_it(tmp_path):
    """Methods of one subject run side by side and read the shared stages for hours (their training stages hold
    read locks on them): a run that finds those stages cached goes on at once; one that must rewrite a stage
    still waits for the readers (here: gives up after run.lock_timeout_s, with the setting named)."""
    out = tmp_path / "out"
    args = [*TOY, f"paths.outputs={out}", "run.lock_timeout_s=3"]
    assert run_cli(*args).returncode == 0
    with flock(out / "synth_a" / ".locks" / "a.lock", shared=True, timeout_s=0.0, what="a reader of stage a"):
        cached = run_cli(*args)
        assert cached.returncode == 0, cached.stderr
        assert all(f"{s}          cached" in cached.stdout for s in "abcd"), cached.stdout
        forced = run_cli(*args, "run.only=a", "run.force=true")
    assert forced.returncode != 0 and "run.lock_timeout_s" in forced.stderr + forced.stdout, forced.stderr


def test_cli_bad_config_is_one_clear_error(tmp_path):
    result = run_cli(*TOY, f"paths.outputs={tmp_path / 'out'}", "run.only=fitt")
    assert result.returncode == 2
    assert "interactavatar: error: invalid config" in result.stderr
    assert "run.only=fitt: unknown stage" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out" / "synth_a").exists()

    result = run_cli(*TOY, f"paths.outputs={tmp_path / 'out'}", "run.force=maybe")
    assert result.returncode == 2
    assert "run.force: Value 'maybe' is not a valid bool" in result.stderr


def test_cli_failing_stage_exits_nonzero_with_message(tmp_path):
    result = run_cli(*TOY, f"paths.outputs={tmp_path / 'out'}", "++stage.a.fail=true")
    assert result.returncode == 1
    assert "stage 'a' failed: RuntimeError: toy stage a was told to fail" in result.stderr


def test_multirun_over_two_subjects_with_local_launcher(tmp_path):
    out = tmp_path / "out"
    result = run_cli("-m", "subject=s1,s2", "hydra/launcher=local", *TOY, f"paths.outputs={out}")
    assert result.returncode == 0, result.stderr
    for subject in ("s1", "s2"):
        assert (out / subject / "c" / "c.txt").read_text() == "a=1\nb=1\nc=1\n"
        assert json.loads((out / subject / "d" / "_manifest.json").read_text())["config"]["subject"] == subject
    assert "Joblib" in result.stdout + result.stderr
