"""``recorded_plan``: what the runner would compute again, judged from the manifests on disk alone (what a reader of a
finished run, the PLY export, checks), on the toy DAG a -> b -> c, a -> d. It agrees with the runner's own plan for
the settings the artifacts were computed with."""

from __future__ import annotations

from pathlib import Path

from pipeline.cli import run_app
from pipeline.runner import recorded_plan
from pipeline.workspace import Artifact, Workspace
from tests.toy_dag import REGISTRY


def _recorded(cfg, target: str = "c", verify: tuple[str, ...] = ()) -> dict[str, str | None]:
    ws = Workspace(Path(cfg.paths.outputs), cfg.subject)
    return {r.artifact.stage: r.stale for r in recorded_plan(ws, REGISTRY, Artifact(target), verify)}


def test_a_republished_input_makes_what_was_computed_from_it_stale_as_the_runners_plan_says(toy_cfg) -> None:
    run_app(toy_cfg())
    assert _recorded(toy_cfg(), verify=("a", "b", "c")) == {"a": None, "b": None, "c": None}  # d: not c's input
    run_app(toy_cfg("stage.a.value=5", "run.only=a"))  # a republished; b and c were computed from the old a
    plan = {r.stage: r.reason for r in run_app(toy_cfg("stage.a.value=5", "run.dry=true")) if r.action == "would run"}
    assert _recorded(toy_cfg()) == {"a": None, "b": plan["b"], "c": plan["c"]}
    assert plan == {"b": "upstream changed: a", "c": "upstream reruns: b", "d": "upstream changed: a"}


def test_outputs_are_hashed_only_where_asked_and_a_missing_artifact_is_named(toy_cfg) -> None:
    cfg = toy_cfg()
    run_app(cfg)
    root = Path(cfg.paths.outputs) / cfg.subject
    (root / "b" / "b.txt").write_text("edited\n")
    assert _recorded(cfg) == {"a": None, "b": None, "c": None}  # the manifests alone agree
    assert _recorded(cfg, verify=("b",)) == {
        "a": None,
        "b": "outputs corrupted: b.txt (hash mismatch)",
        "c": ("upstream reruns: b"),
    }
    (root / "a" / "_manifest.json").unlink()
    assert _recorded(cfg, target="b") == {"a": "outputs missing", "b": "upstream reruns: a"}
