"""Behaviour of the cached DAG runner on the toy DAG a -> b -> c, a -> d."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from pipeline.manifest import MANIFEST_NAME
from pipeline.runner import MissingUpstream, StageFailed


def actions(reports) -> dict[str, str]:
    return {r.stage: r.action for r in reports}


def reasons(reports) -> dict[str, str]:
    return {r.stage: r.reason for r in reports}


def subject_dir(cfg) -> Path:
    return Path(cfg.paths.outputs) / cfg.subject


def test_first_run_runs_everything_second_is_all_cached(toy_cfg, capsys):
    first = run_app(toy_cfg())
    assert actions(first) == {s: "run" for s in "abcd"}
    assert reasons(first)["a"] == "outputs missing: never run"
    second = run_app(toy_cfg())
    assert actions(second) == {s: "cached" for s in "abcd"}
    assert all(r.reason == "cached" for r in second)
    out = capsys.readouterr().out
    assert "cached" in out and "value" in out  # decision lines and the metrics table


def test_config_change_reruns_stage_and_exactly_its_descendants(toy_cfg):
    run_app(toy_cfg())
    reports = run_app(toy_cfg("stage.b.value=7"))
    assert actions(reports) == {"a": "cached", "b": "run", "c": "run", "d": "cached"}
    assert reasons(reports)["b"] == "config changed: stage.b.value"
    assert reasons(reports)["c"] == "upstream changed: b"
    cfg = toy_cfg("stage.b.value=7")
    assert (subject_dir(cfg) / "c" / "c.txt").read_text() == "a=1\nb=7\nc=1\n"


def test_code_version_change_is_reported(toy_cfg, monkeypatch):
    import dataclasses

    from tests import toy_dag

    run_app(toy_cfg())
    bumped = dataclasses.replace(toy_dag.REGISTRY["d"], version="2")
    monkeypatch.setitem(toy_dag.REGISTRY._stages, "d", bumped)
    reports = run_app(toy_cfg())
    assert reasons(reports)["d"] == "code version changed: 1 -> 2"
    assert actions(reports) == {"a": "cached", "b": "cached", "c": "cached", "d": "run"}


def test_force_reruns_selected_stages(toy_cfg):
    run_app(toy_cfg())
    reports = run_app(toy_cfg("run.force=true", "run.until=b"))
    assert actions(reports) == {"a": "run", "b": "run"}
    assert reasons(reports) == {"a": "forced", "b": "forced"}
    # c and d read the recomputed a/b, whose content is identical: still cached.
    assert actions(run_app(toy_cfg())) == {s: "cached" for s in "abcd"}


def test_selection_only_from_until(toy_cfg):
    run_app(toy_cfg())
    assert list(actions(run_app(toy_cfg("run.only=c")))) == ["c"]
    assert list(actions(run_app(toy_cfg("run.from=b")))) == ["b", "c"]
    assert list(actions(run_app(toy_cfg("run.until=c")))) == ["a", "b", "c"]
    assert list(actions(run_app(toy_cfg("run.from=a", "run.until=b")))) == ["a", "b"]


def test_only_without_complete_upstream_fails_before_writing(toy_cfg):
    cfg = toy_cfg("run.only=b")
    with pytest.raises(MissingUpstream, match="reads 'a', which has no complete artifact"):
        run_app(cfg)
    assert not (subject_dir(cfg) / "b").exists()


def test_failing_stage_leaves_no_artifact_and_next_run_redoes_it(toy_cfg):
    with pytest.raises(StageFailed, match="toy stage a was told to fail"):
        run_app(toy_cfg("++stage.a.fail=true"))
    cfg = toy_cfg()
    assert not (subject_dir(cfg) / "a").exists()
    assert list((subject_dir(cfg) / ".tmp").iterdir()) == []
    reports = run_app(cfg)
    assert actions(reports)["a"] == "run"


def test_a_failure_names_the_stage_output_not_its_removed_temporary_folder(toy_cfg):
    cfg = toy_cfg("++stage.a.fail=true")
    with pytest.raises(StageFailed) as caught:
        run_app(cfg)
    assert str(caught.value).endswith(f"; nothing was written to {subject_dir(cfg) / 'a'}"), str(caught.value)
    tmp, out = Path("/o/.tmp/a-1f"), Path("/o/a")
    said = str(StageFailed("a", ValueError(f"{tmp}/a.txt: not finite"), written=(tmp, out)))
    assert said == "stage 'a' failed: ValueError: /o/a/a.txt: not finite; nothing was written to /o/a"


def test_checkpoint_in_scratch_survives_a_failure_and_is_removed_on_success(toy_cfg):
    cfg = toy_cfg("++stage.a.fail_once=true")
    with pytest.raises(StageFailed, match="failed after a checkpoint"):
        run_app(cfg)
    scratch = list((subject_dir(cfg) / ".scratch").glob("a-*"))
    assert len(scratch) == 1 and (scratch[0] / "checkpoint.txt").exists()
    run_app(cfg)
    assert (subject_dir(cfg) / "a" / "parts" / "resumed.txt").read_text() == "half done\n"
    assert not list((subject_dir(cfg) / ".scratch").glob("a-*"))


def test_failing_rerun_keeps_old_whole_artifact(toy_cfg):
    run_app(toy_cfg())
    with pytest.raises(StageFailed):
        run_app(toy_cfg("++stage.a.fail=true", "stage.a.value=3"))
    cfg = toy_cfg()
    assert (subject_dir(cfg) / "a" / "a.txt").read_text() == "a=1\n"
    assert actions(run_app(cfg)) == {s: "cached" for s in "abcd"}


@pytest.mark.parametrize(
    ("tamper", "expected"),
    [
        (lambda d: (d / "b.txt").write_text("a=1\nb=666\n"), "outputs corrupted: b.txt (hash mismatch)"),
        (lambda d: (d / "b.txt").unlink(), "outputs missing: b.txt"),
        (lambda d: (d / "parts" / "extra.bin").write_bytes(b"x"), "outputs changed: unexpected file parts/extra.bin"),
        (lambda d: (d / MANIFEST_NAME).unlink(), "outputs missing"),
        (lambda d: (d / MANIFEST_NAME).write_text("{not json"), "manifest corrupted"),
    ],
    ids=["edited-output", "deleted-output", "extra-file", "deleted-manifest", "garbled-manifest"],
)
def test_tampered_artifacts_are_detected(toy_cfg, tamper, expected):
    run_app(toy_cfg())
    cfg = toy_cfg()
    tamper(subject_dir(cfg) / "b")
    reports = run_app(cfg)
    assert reasons(reports)["b"].startswith(expected)
    assert actions(reports) == {"a": "cached", "b": "run", "c": "cached", "d": "cached"}
    assert (subject_dir(cfg) / "b" / "b.txt").read_text() == "a=1\nb=1\n"


def test_hand_edited_manifest_is_detected(toy_cfg):
    run_app(toy_cfg())
    cfg = toy_cfg()
    path = subject_dir(cfg) / "a" / MANIFEST_NAME
    body = json.loads(path.read_text())
    body["outputs"]["a.txt"] = "0" * 64  # make the stage look fine for a different file content
    path.write_text(json.dumps(body))
    reports = run_app(cfg)
    assert reasons(reports)["a"].startswith("manifest corrupted")
    assert "does not match its digest" in reasons(reports)["a"]


def test_dry_run_plans_and_writes_nothing(toy_cfg, capsys):
    cfg = toy_cfg("run.dry=true")
    reports = run_app(cfg)
    assert actions(reports) == {s: "would run" for s in "abcd"}
    assert reasons(reports)["b"] == "upstream reruns: a"
    assert not subject_dir(cfg).exists()
    run_app(toy_cfg())
    reports = run_app(toy_cfg("run.dry=true", "stage.d.value=5"))
    assert actions(reports) == {"a": "cached", "b": "cached", "c": "cached", "d": "would run"}
    assert "dry run" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("run.only=nope", "run.only=nope: unknown stage; choose one of a, b, c, d"),
        ("run.until=zzz", "run.until=zzz: unknown stage"),
        ("stage.a.value=abc", "stage.a.value: Value 'abc' of type 'str' could not be converted to Integer"),
        ("+stage.a.typo=1", "stage.a.typo: not a setting of stage.a"),
        ("subject=''", "subject='': use letters, digits"),
    ],
)
def test_bad_config_fails_before_any_stage(toy_cfg, override, message):
    cfg = toy_cfg(override)
    with pytest.raises(ConfigError) as info:
        run_app(cfg)
    assert message in str(info.value)
    assert not Path(cfg.paths.outputs).exists()


def test_stage_reading_undeclared_input_is_a_clear_error(tmp_path):
    from pipeline.stage import StageContext

    ctx = StageContext(cfg=None, subject="s", out_dir=tmp_path, inputs={"a": tmp_path})  # type: ignore[arg-type]
    with pytest.raises(KeyError, match="does not declare it"):
        ctx.input_dir("b")
