"""Regression tests of the fault catalogue (issue 9): the cache never certifies what it did not compute."""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.manifest import read_manifest, write_manifest
from pipeline.runner import StageFailed
from tests.conftest import REPO, TOY_OVERRIDES, cli_command, cli_env, run_cli, wait_for

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_a_stage_reads_exactly_the_inputs_its_manifest_names_while_another_run_rewrites_them(tmp_path):
    """Case 1: `run.only=c run.force=true` while another run republishes c's input b with another config."""
    out = tmp_path / "out"
    base = [*TOY, f"paths.outputs={out}"]
    assert run_cli(*base).returncode == 0
    subject = out / "synth_a"
    old_b = read_manifest(subject / "b").output_digest
    reader = subprocess.Popen(
        cli_command(*base, "run.only=c", "run.force=true", "++stage.c.sleep_s=3"),
        cwd=REPO,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: any((subject / ".tmp").glob("c-*/parts/half.txt")))  # c has read b once
        writer = run_cli(*base, "run.only=b", "run.force=true", "stage.b.value=7")
        reader_out, reader_err = reader.communicate(timeout=60)
    finally:
        reader.kill()
    assert reader.returncode == 0 and writer.returncode == 0, reader_err + writer.stderr
    assert not (subject / "c" / "parts" / "mixed.txt").exists(), "c read two versions of b"
    assert (subject / "c" / "c.txt").read_text() == "a=1\nb=1\nc=1\n"
    assert read_manifest(subject / "c").upstream["b"] == old_b  # c names the b it read
    assert (subject / "b" / "b.txt").read_text() == "a=1\nb=7\n"  # the writer waited, then published
    after = run_cli(*base, "stage.b.value=7", "++stage.c.sleep_s=3")
    assert "c          run       upstream changed: b" in after.stdout


def test_an_input_replaced_without_the_lock_fails_the_stage_and_publishes_nothing(toy_cfg, monkeypatch):
    """Case 1, second line of defence: inputs are checked again at publish time."""
    from tests import toy_dag

    run_app(toy_cfg())
    subject = Path(toy_cfg().paths.outputs) / "synth_a"
    before = (subject / "c" / "_manifest.json").read_text()
    original = toy_dag.REGISTRY["c"]

    def rogue(ctx):  # a writer that ignores the locks replaces b while c runs
        original.fn(ctx)
        manifest = read_manifest(ctx.input_dir("b"))
        manifest.outputs = {**manifest.outputs, "rogue.txt": "0" * 64}
        write_manifest(ctx.input_dir("b"), manifest)

    monkeypatch.setitem(toy_dag.REGISTRY._stages, "c", dataclasses.replace(original, fn=rogue))
    with pytest.raises(StageFailed, match="input 'b' was replaced while the stage ran"):
        run_app(toy_cfg("run.only=c", "run.force=true"))
    assert (subject / "c" / "_manifest.json").read_text() == before


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "quality.warmup_steps=abc",
            "quality.warmup_steps: Value 'abc' of type 'str' could not be converted to Integer",
        ),
        ("quality.warmup_steps=-5", "quality.warmup_steps=-5: must be at least 1"),
        ("quality.warmup_steps=0", "quality.warmup_steps=0: must be at least 1"),
        ("quality.gaussians_per_triangle=0", "quality.gaussians_per_triangle=0: must be between 1 and 1000"),
        ("quality.image_size=4", "quality.image_size=4: must be between 16 and 8192"),
    ],
)
def test_quality_block_is_typed_and_range_checked_before_any_stage_runs(toy_cfg, override, message):
    """Case 4: a bad preset value fails before anything is written, naming the key."""
    from pipeline.config import ConfigError

    cfg = toy_cfg(override)
    with pytest.raises(ConfigError) as err:
        run_app(cfg)
    assert message in str(err.value)
    assert not (Path(cfg.paths.outputs) / "synth_a").exists()


def test_every_shipped_quality_preset_passes_its_own_schema(toy_cfg):
    for preset in ("smoke", "draft", "standard", "paper"):
        assert run_app(toy_cfg(f"quality={preset}", "run.dry=true"))


@pytest.mark.parametrize("subject", ["foo bar", "-rf", "a/b", "_x", ".hidden"])
def test_subject_rule_is_enforced_as_stated_in_one_line(tmp_path, subject):
    """Case 6: the check enforces the rule the message states."""
    result = run_cli(*TOY, f"paths.outputs={tmp_path / 'out'}", f"subject={subject}")
    assert result.returncode == 2, result.stdout
    assert result.stderr.strip().splitlines() == [
        f"interactavatar: error: invalid config: subject={subject!r}: use letters, digits, '-' or '_', starting with "
        "a letter or digit, at most 64 characters, e.g. subject=synth_a"
    ]
    assert "Traceback" not in result.stderr


def test_outputs_pointing_at_a_file_is_one_clear_error(tmp_path):
    """Case 6: `paths.outputs` at a regular file: one line naming the key, no traceback."""
    target = tmp_path / "afile"
    target.write_text("")
    result = run_cli(*TOY, f"paths.outputs={target}")
    assert result.returncode == 2
    assert f"paths.outputs={target}: {target} is a file, not a folder" in result.stderr
    assert "Traceback" not in result.stderr


def test_outputs_on_a_read_only_file_system_is_one_clear_error(tmp_path):
    """Case 6: `paths.outputs` on a read-only mount (a real one: tmpfs mounted read-only)."""
    mount = tmp_path / "ro"
    mount.mkdir()
    if (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64k,ro", "tmpfs", str(mount)], capture_output=True, check=False
        ).returncode
        != 0
    ):
        pytest.skip("needs root to mount a read-only tmpfs")
    try:
        result = run_cli(*TOY, f"paths.outputs={mount / 'out'}")
    finally:
        subprocess.run(["umount", str(mount)], check=False)
    assert result.returncode == 2
    assert f"paths.outputs={mount / 'out'}: {mount} is not writable (read-only file system" in result.stderr
    assert "Traceback" not in result.stderr


def test_leftovers_of_a_killed_run_are_cleaned_when_the_stage_is_found_cached(tmp_path):
    """Case 9: `.tmp/<stage>-*` and `.scratch/<stage>-*` of a killed run do not stay forever."""
    out = tmp_path / "out"
    base = [*TOY, f"paths.outputs={out}", "++stage.a.sleep_s=1"]
    assert run_cli(*base).returncode == 0
    subject = out / "synth_a"
    killed = subprocess.Popen(
        cli_command(*base, "run.force=true", "run.only=a", "++stage.a.sleep_s=1"),
        cwd=REPO,
        env=cli_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for(lambda: any((subject / ".tmp").glob("a-*/parts/half.txt")))
        killed.kill()
        killed.wait(timeout=30)
    finally:
        killed.kill()
    assert list((subject / ".tmp").glob("a-*")) and list((subject / ".scratch").glob("a-*"))
    result = run_cli(*base)
    assert "a          cached" in result.stdout
    assert not list((subject / ".tmp").glob("a-*")), "a killed run's temporary dir stayed"
    assert not list((subject / ".scratch").glob("a-*")), "a killed run's scratch dir stayed"


def test_a_failed_run_leaves_no_empty_scratch_dir(toy_cfg):
    """Case 9: the scratch dir is made for the stage, and removed when it failed without a checkpoint."""
    cfg = toy_cfg("++stage.a.fail=true")
    with pytest.raises(StageFailed):
        run_app(cfg)
    subject = Path(cfg.paths.outputs) / "synth_a"
    assert not list((subject / ".scratch").glob("a-*"))
    assert not list((subject / ".tmp").glob("a-*"))


def test_a_failed_run_keeps_its_checkpoint_for_the_next_run(toy_cfg):
    cfg = toy_cfg("++stage.a.fail_once=true")
    with pytest.raises(StageFailed):
        run_app(cfg)
    assert list((Path(cfg.paths.outputs) / "synth_a" / ".scratch").glob("a-*/checkpoint.txt"))


def test_warmup_key_leaves_out_the_checkpoint_interval_and_every_preset_checkpoints():
    """Case 9: changing checkpoint_every does not retrain a finished warm-up; smoke exercises checkpoints."""
    from pipeline.config import config_subset
    from stages import REGISTRY
    from tests.conftest import compose_cfg

    warmup = REGISTRY["warmup"]
    subset = lambda *o: config_subset(compose_cfg(list(o)), warmup.config_keys, warmup.cache_exclude)  # noqa: E731
    assert subset("stage.warmup.checkpoint_every=7") == subset("stage.warmup.checkpoint_every=500")
    assert subset("stage.warmup.seed=1") != subset("stage.warmup.seed=2")
    for preset in ("smoke", "draft", "standard", "paper"):
        cfg = compose_cfg([f"quality={preset}"])
        assert 0 < cfg.stage.warmup.checkpoint_every < cfg.quality.warmup_steps, preset


def test_a_resumed_stage_counts_the_killed_runs_work_up_to_its_checkpoint(toy_cfg):
    """Issue 36 item 13: a resumed stage's manifest carries the earlier run's time up to its checkpoint
    (``timings.resumed_s``); a stage that ran in one go has none; nothing is left in scratch."""
    cfg = toy_cfg("++stage.a.fail_once=true", "++stage.a.sleep_s=0.4")
    with pytest.raises(StageFailed):
        run_app(cfg)
    run_app(cfg)
    root = Path(cfg.paths.outputs) / "synth_a"
    timings = json.loads((root / "a" / "_manifest.json").read_text())["timings"]
    assert 0.4 <= timings["resumed_s"] < 0.4 + 5.0  # the first run slept 0.4 s before its checkpoint
    assert timings["wall_s"] >= 0.4  # the resumed run's own time, apart
    assert "resumed_s" not in json.loads((root / "b" / "_manifest.json").read_text())["timings"]
    assert not list((root / ".scratch").glob("a-*"))


def test_a_failure_before_any_checkpoint_leaves_no_scratch_and_carries_nothing(toy_cfg):
    cfg = toy_cfg("++stage.a.fail=true")
    with pytest.raises(StageFailed):
        run_app(cfg)
    root = Path(cfg.paths.outputs) / "synth_a"
    assert not list((root / ".scratch").glob("a-*"))  # the attempt marker alone is not worth keeping
    run_app(toy_cfg())
    assert "resumed_s" not in json.loads((root / "a" / "_manifest.json").read_text())["timings"]
