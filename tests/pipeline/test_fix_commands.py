"""Fix commands in messages repeat the run's own overrides (issue 36 item 12): run as printed, they compute in
the same DAG instead of building a new one elsewhere or refitting a shared stage."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from pipeline.config import fix_command
from pipeline.workspace import method_run, run_overrides
from tests.conftest import TOY_OVERRIDES, compose_cfg, run_cli


def _cfg_with(overrides: list[str]):
    cfg = compose_cfg([])
    OmegaConf.update(cfg, "run.overrides", overrides)
    return cfg


def test_the_runs_overrides_are_repeated_except_what_selects_the_run():
    cfg = _cfg_with(
        [
            "paths.outputs=/data/out x",
            "fit.source=ground_truth",
            "quality=draft",
            "method=gaussian_avatars",
            "method.label=GA",
            "seed=2",
            "run.only=compare",
            "+run.force=true",
            "stage.warmup.seed=3",
        ]
    )
    assert fix_command(cfg, "method=interactavatar", "run.until=evaluate") == (
        "interactavatar 'paths.outputs=/data/out x' fit.source=ground_truth quality=draft stage.warmup.seed=3 "
        "method=interactavatar run.until=evaluate"
    )
    # an argument wins over the run's override of the same key
    assert fix_command(cfg, "quality=standard") == (
        "interactavatar 'paths.outputs=/data/out x' fit.source=ground_truth stage.warmup.seed=3 quality=standard"
    )
    assert fix_command(compose_cfg([]), "run.until=fit") == "interactavatar run.until=fit"  # run_app, no CLI


def test_run_overrides_select_the_run_folder():
    for method, seed in (("interactavatar", 0), ("no_pbd", 2), ("my-seed-method", 0), ("a-seed3x", 1)):
        overrides = dict(o.split("=") for o in run_overrides(method_run(method, seed)))
        assert (overrides["method"], int(overrides.get("seed", 0))) == (method, seed)


def test_the_cli_prints_a_missing_input_with_the_command_lines_overrides(tmp_path: Path):
    """Before: `run it first (e.g. interactavatar subject=synth_a run.until=a)`, which computes `a` in ./outputs
    with the app's own DAG, not here."""
    out = tmp_path / "out"
    proc = run_cli(*TOY_OVERRIDES, f"paths.outputs={out}", "run.progress=false", "run.only=b")
    assert proc.returncode == 1, proc.stderr
    assert f"run it first (e.g. interactavatar {' '.join(TOY_OVERRIDES[:1])} 'stage=[]'" in proc.stderr
    assert f"paths.outputs={out} subject=synth_a run.until=a)" in proc.stderr


def test_runs_the_comparison_left_out_are_printed_with_the_command_that_recomputes_them():
    from pipeline.cli import comparison_fixes
    from pipeline.runner import StageReport

    cfg = _cfg_with(["paths.outputs=/o", "fit.source=ground_truth", "run.only=compare"])
    reports = [StageReport("compare", "run", "", metrics={"methods_stale": "no_pbd-seed2", "methods_corrupt": "-"})]
    assert comparison_fixes(cfg, reports) == [
        "comparison: no_pbd-seed2 left out (stale); recompute it with `interactavatar paths.outputs=/o "
        "fit.source=ground_truth method=no_pbd seed=2 run.until=evaluate`, then "
        "`interactavatar paths.outputs=/o fit.source=ground_truth run.only=compare`"
    ]
    assert comparison_fixes(cfg, [StageReport("compare", "cached", "", metrics={"methods_stale": "-"})]) == []
