"""Per-method artifacts: methods side by side under one subject, sharing what they have in common."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from pipeline.registry import RegistryError, StageRegistry
from pipeline.stage import StageContext, stage
from tests.conftest import compose_cfg


@pytest.fixture
def method_cfg(tmp_path: Path):
    def make(method: str, p_value: int = 1, *extra: str):
        return compose_cfg(
            [
                "pipeline.stages_module=tests.toy_methods",
                "stage=[]",
                "+stage.a.value=1",
                "+stage.cmp.methods=[m1,m2,m3]",
                "+stage.cmp.seeds=[0]",
                f"method.name={method}",
                f"+method.p_value={p_value}",
                f"paths.outputs={tmp_path / 'out'}",
                "run.progress=false",
                *extra,
            ]
        )

    return make


def actions(reports) -> dict[str, str]:
    return {r.stage: r.action for r in reports}


def test_methods_live_side_by_side_and_share_identical_artifacts(method_cfg, tmp_path):
    root = tmp_path / "out" / "synth_a"
    first = run_app(method_cfg("m1"))
    assert actions(first) == {"a": "run", "p": "run", "q": "run", "cmp": "run"}
    assert (root / "methods" / "m1" / "q" / "q.txt").read_text() == "a=1\np=1\nq=m1\n"
    assert (root / "cmp" / "cmp.txt").read_text() == "m1: a=1\np=1\nq=m1\n"

    second = run_app(method_cfg("m2"))  # same p_value: p is m1's, shared by hard links, not recomputed
    assert actions(second) == {"a": "cached", "p": "shared", "q": "run", "cmp": "run"}
    assert "same key as method m1" in {r.stage: r.reason for r in second}["p"]
    m1_p, m2_p = (root / "methods" / m / "p" / "p.txt" for m in ("m1", "m2"))
    assert os.path.samefile(m1_p, m2_p)
    assert {r.stage: r.reason for r in second}["cmp"] == "upstream changed: q@m2"
    assert (root / "cmp" / "cmp.txt").read_text().count("q=") == 2

    third = run_app(method_cfg("m3", 5))  # another p_value: its own p
    assert actions(third) == {"a": "cached", "p": "run", "q": "run", "cmp": "run"}
    assert (root / "methods" / "m3" / "q" / "q.txt").read_text() == "a=1\np=5\nq=m3\n"

    again = run_app(method_cfg("m1"))  # adding methods recomputed nothing of m1
    assert actions(again) == {"a": "cached", "p": "cached", "q": "cached", "cmp": "cached"}
    assert again[-1].metrics["methods"] == 3


def test_each_seed_is_a_run_of_its_own_beside_the_others(method_cfg, tmp_path):
    """seed=k keeps the method's per-method artifacts in methods/<method>-seed<k>/ (seed 0 where it always was);
    a stage that does not depend on the seed is shared, and the comparison reads every listed seed."""
    root = tmp_path / "out" / "synth_a"
    run_app(method_cfg("m1"))
    seeded = run_app(method_cfg("m1", 1, "seed=1", "stage.cmp.seeds=[0,1]"))
    assert actions(seeded) == {"a": "cached", "p": "shared", "q": "run", "cmp": "run"}
    assert (root / "methods" / "m1-seed1" / "q" / "q.txt").read_text() == "a=1\np=1\nq=m1-seed1\n"
    assert (root / "methods" / "m1" / "q" / "q.txt").read_text() == "a=1\np=1\nq=m1\n"
    assert (root / "cmp" / "cmp.txt").read_text() == "m1: a=1\np=1\nq=m1\nm1-seed1: a=1\np=1\nq=m1-seed1\n"
    with pytest.raises(ConfigError, match="seed=-1"):
        run_app(method_cfg("m1", 1, "seed=-1"))
    with pytest.raises(ConfigError, match="stage.cmp.seeds"):
        run_app(method_cfg("m1", 1, "stage.cmp.seeds=[]"))


def test_a_cross_method_reader_is_told_which_listed_artifacts_are_corrupt(method_cfg, tmp_path):
    """Issue 36 item 11: a corrupt artifact was indistinguishable from a missing one for the comparison."""
    root = tmp_path / "out" / "synth_a"
    run_app(method_cfg("m1"))
    run_app(method_cfg("m2"))
    (root / "methods" / "m2" / "q" / "q.txt").write_text("tampered\n")
    run_app(method_cfg("m1", 1, "run.only=cmp"))
    text = (root / "cmp" / "cmp.txt").read_text()
    assert text.startswith("m1: ") and "m2: a=" not in text
    assert "unusable m2: q: " in text and "q.txt" in text


def test_a_method_s_change_reruns_only_that_method(method_cfg, tmp_path):
    run_app(method_cfg("m1"))
    run_app(method_cfg("m2"))
    changed = run_app(method_cfg("m2", 7))
    assert actions(changed) == {"a": "cached", "p": "run", "q": "run", "cmp": "run"}
    assert actions(run_app(method_cfg("m1"))) == {"a": "cached", "p": "cached", "q": "cached", "cmp": "cached"}


def test_forced_per_method_stage_is_recomputed_not_shared(method_cfg, tmp_path):
    run_app(method_cfg("m1"))
    forced = run_app(method_cfg("m2", 1, "run.force=true", "run.only=p"))
    assert actions(forced) == {"p": "run"}
    root = tmp_path / "out" / "synth_a" / "methods"
    assert not os.path.samefile(root / "m1" / "p" / "p.txt", root / "m2" / "p" / "p.txt")


def test_dry_run_names_the_method_it_would_share_with(method_cfg):
    run_app(method_cfg("m1"))
    plan = run_app(method_cfg("m2", 1, "run.dry=true"))
    reasons = {r.stage: r.reason for r in plan}
    assert "shared with method m1" in reasons["p"]
    assert reasons["cmp"] == "upstream reruns: q@m2"


def test_bad_method_names_are_refused(method_cfg):
    with pytest.raises(ConfigError, match="method.name='../x'"):
        run_app(method_cfg("'../x'"))
    with pytest.raises(ConfigError, match="stage.cmp.methods"):
        run_app(method_cfg("m1", 1, "stage.cmp.methods=[m1,'a b']"))


def _noop(ctx: StageContext) -> None:
    """Does nothing."""


def test_a_shared_stage_cannot_read_a_per_method_one_directly():
    per = stage("per", outputs=("x",), per_method=True)(_noop)
    shared = stage("shared", inputs=("per",), outputs=("y",))(_noop)
    with pytest.raises(RegistryError, match="per_method"):
        StageRegistry([per, shared]).topological()
    plain = stage("plain", outputs=("x",))(_noop)
    cross = stage("cross", outputs=("y",), cross_method_inputs=("plain",), methods_key="k")(_noop)
    with pytest.raises(RegistryError, match="shared by every method"):
        StageRegistry([plain, cross]).topological()


def test_a_methods_yaml_sets_run_and_root_settings_the_command_line_still_overrides(tmp_path: Path) -> None:
    """The root config's own values used to be merged after the method's file, so a method could not set ``run.*``
    (nor ``splatting.*``, ``fit.*``, ...): what it said was silently replaced by the root's defaults."""
    (tmp_path / "method").mkdir()
    (tmp_path / "method" / "bf16_method.yaml").write_text(
        "# @package _global_\ndefaults:\n  - interactavatar\nmethod:\n  name: bf16_method\n"
        "run:\n  precision: bf16\n  lock_timeout_s: 60\nsplatting:\n  walk_every: 7\n"
    )
    user = [f"hydra.searchpath=[file://{tmp_path}]", "method=bf16_method"]
    cfg = compose_cfg(user)
    assert (cfg.method.name, cfg.run.precision, cfg.run.lock_timeout_s, cfg.splatting.walk_every) == (
        "bf16_method",
        "bf16",
        60,
        7,
    )
    assert cfg.run.device == "auto" and cfg.method.representation == "bound"  # the rest as the root and its base say
    assert compose_cfg([*user, "run.precision=fp32"]).run.precision == "fp32"
