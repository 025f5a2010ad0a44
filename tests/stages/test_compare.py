"""The comparison's arithmetic against brute force: frame groups, showcase frames, crops, cost."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy.stats import ttest_ind

from avatar.metrics.stats import welch_p
from data_schemas.metrics import CONTACT_GROUPS
from reporting.comparison_figure import crop_box
from reporting.comparison_tables import comparison_rows, comparison_tables, lookup, run_cost
from reporting.method_runs import SHARED_STAGES, MethodRun, stale_reason
from stages.evaluate import showcase_pairs
from tests.conftest import CONF_DIR


def _method_config(name: str) -> dict:
    """``method`` of conf/method/<name>.yaml as an evaluation records it (its role in the tables), or {}."""
    path = CONF_DIR / "method" / f"{name}.yaml"
    return OmegaConf.to_container(OmegaConf.load(path).method) if path.is_file() else {}


def _run(name: str, warmup_key: str = "k0", seed: int = 0, train_seed: int = 0, shift: float = 0.0) -> MethodRun:
    """A method (training run ``train_seed``; every PSNR raised by ``shift`` dB) with metrics of 2 splits x 4
    regions x 2 cameras x 5 frames, frames 1 and 3 with contact, the hand region absent (NaN) in frame 0 and one
    infinite PSNR (a perfect image)."""
    rng = np.random.default_rng(seed)
    rows = [
        (split, region, cam, frame)
        for split in ("novel_view", "self_reenact")
        for region in ("full", "hand", "face", "interaction")
        for cam in ("c0", "c1")
        for frame in range(5)
    ]
    split, region, cam, frame = (np.array(col) for col in zip(*rows))
    psnr, ssim, lpips = rng.uniform(20, 30, len(rows)), rng.uniform(0.8, 0.9, len(rows)), rng.uniform(0, 0.1, len(rows))
    psnr += shift
    absent = (region == "hand") & (frame == 0)
    psnr[absent] = ssim[absent] = lpips[absent] = np.nan
    psnr[(region == "face") & (frame == 2) & (cam == "c1")] = np.inf
    metrics = {
        "method": np.full(len(rows), name),
        "split": split,
        "region": region,
        "camera_id": cam,
        "frame": frame,
        "contact": np.isin(frame, [1, 3]),
        "psnr": psnr,
        "ssim": ssim,
        "lpips": lpips,
    }
    manifests = {
        "warmup": {"key": warmup_key, "metrics": {"steps": 20}, "timings": {"wall_s": 10.0}},
        "dynamic": {"metrics": {"steps": 10, "gaussians": 123}, "timings": {"wall_s": 5.0}},
        "evaluate": {"timings": {"wall_s": 2.0}, "config": {"method": _method_config(name)}},
    }
    return MethodRun(name, train_seed, name.upper(), Path("/nonexistent"), metrics, manifests)


def test_rows_are_the_means_of_their_group_ignoring_absent_regions_and_perfect_images():
    runs = [_run("interactavatar"), _run("gaussian_avatars", seed=1)]
    rows = comparison_rows(runs)
    for run in runs:
        t = run.metrics
        for split in ("novel_view", "self_reenact"):
            for region in ("full", "hand", "face", "interaction"):
                for group in CONTACT_GROUPS:
                    sel = (t["split"] == split) & (t["region"] == region)
                    if group != "all":
                        sel &= t["contact"] == (group == "contact")
                    psnr = t["psnr"][sel]
                    expected = np.mean(psnr[np.isfinite(psnr)])
                    got = lookup(rows, run.name, split, region, group)
                    assert got["psnr"] == pytest.approx(expected, rel=1e-12)
                    assert got["lpips"] == pytest.approx(np.nanmean(t["lpips"][sel]), rel=1e-12)
    hand_all = [
        i
        for i in range(len(rows["method"]))
        if rows["method"][i] == "interactavatar"
        and rows["split"][i] == "novel_view"
        and rows["region"][i] == "hand"
        and rows["contact"][i] == "all"
    ]
    assert [rows["images"][i] for i in hand_all] == [8]  # 10 images, frame 0 has no hand in either camera
    assert set(rows["train_steps"]) == {30} and set(rows["gaussians"]) == {123}


def test_a_group_without_images_has_no_row():
    run = _run("interactavatar")
    run.metrics["contact"][:] = False
    rows = comparison_rows([run])
    assert "contact" not in set(rows["contact"]) and {"all", "no_contact"} == set(rows["contact"])


def test_shared_warmups_count_once_in_the_cost():
    runs = [_run("a", "k0"), _run("b", "k0"), _run("c", "k1")]
    shared = {"capture": {"timings": {"wall_s": 100.0}}}
    cost = run_cost(runs, shared)
    assert cost["warmups_trained"] == 2
    assert cost["total_wall_s"] == pytest.approx(100 + 2 * 10 + 3 * (5 + 2))
    assert cost["unshared_wall_s"] == pytest.approx(3 * 100 + 3 * 10 + 3 * (5 + 2))


def test_a_resumed_run_counts_the_killed_runs_work_and_is_marked():
    """Issue 36 item 13: after a resume the training time counted only the resumed part."""
    run = _run("interactavatar")
    run.manifests["dynamic"]["timings"]["resumed_s"] = 7.0
    assert run.train_wall_s == pytest.approx(15.0 + 7.0) and run.resumed and not _run("no_pbd").resumed
    runs = [run, _run("gaussian_avatars")]
    tables = comparison_tables(
        runs, comparison_rows(runs), [], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    budget = next(t for t in tables["tables"] if t["title"] == "Training budget")
    assert [row[3] for row in budget["rows"]] == ["22 (resumed)", "15"]
    assert any("(resumed)" in n for n in tables["notes"])


def test_tables_say_whether_the_budget_was_the_same_and_what_is_missing():
    same = comparison_tables(
        [_run("interactavatar"), _run("gaussian_avatars")],
        comparison_rows([_run("interactavatar"), _run("gaussian_avatars")]),
        [("no_pbd", 0)],
        {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0},
    )
    assert any("same number of optimisation steps" in n for n in same["notes"])
    assert any("method=no_pbd" in n for n in same["notes"])
    table1 = same["tables"][0]
    assert [row[1] for row in table1["rows"]] == ["GAUSSIAN_AVATARS", "INTERACTAVATAR"] * 2  # the paper's order
    assert table1["rows"][1][5] == "29.85"  # the paper's novel-view PSNR beside ours
    other = _run("no_patch")
    other.manifests["dynamic"]["metrics"]["steps"] = 11
    unfair = comparison_tables(
        [_run("interactavatar"), other],
        comparison_rows([_run("interactavatar"), other]),
        [],
        {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0},
    )
    assert any("not fair" in n for n in unfair["notes"])


def test_a_method_stands_where_its_own_config_puts_it():
    """Issue 37: a method's tables, position, paper figures and full-model role come from its config (as its
    evaluation recorded it), not from a list in the stage: an eighth method needs no edit here."""
    eighth = _run("eighth")
    eighth.manifests["evaluate"]["config"]["method"] = {
        "label": "Eighth",
        "tables": {"baselines": 0, "ablations": 9},
        "full_model": False,
        "paper": {"novel_view": [30.5, 0.95, 0.02]},
    }
    silent = _run("no_role")  # declares nothing: in the comparison, in no table
    runs = [_run("interactavatar"), _run("gaussian_avatars"), eighth, silent]
    tables = comparison_tables(
        runs, comparison_rows(runs), [], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    table1, table2 = tables["tables"][0], tables["tables"][1]
    novel1 = [row for row in table1["rows"] if row[0] == "novel_view"]
    assert [row[1] for row in novel1] == ["EIGHTH", "GAUSSIAN_AVATARS", "INTERACTAVATAR"]
    assert novel1[0][5] == "30.50"  # its own paper figure
    assert [row[1] for row in table2["rows"] if row[0] == "novel_view"] == ["INTERACTAVATAR", "EIGHTH"]
    assert all("NO_ROLE" not in row for t in (table1, table2) for row in t["rows"])
    assert "NO_ROLE" in [row[0] for row in next(t for t in tables["tables"] if t["title"] == "Training budget")["rows"]]


def test_without_a_full_model_there_is_no_seeds_table():
    runs = [_run(name, seed=seed, train_seed=seed) for name in ("gaussian_avatars", "no_pbd") for seed in (0, 1)]
    tables = comparison_tables(
        runs, comparison_rows(runs), [], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    assert not any(t["title"].startswith("Seeds") for t in tables["tables"])
    with_full = runs + [_run("interactavatar", seed=s, train_seed=s) for s in (0, 1)]
    tables = comparison_tables(
        with_full, comparison_rows(with_full), [], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    assert any(t["title"].startswith("Seeds: INTERACTAVATAR's PSNR") for t in tables["tables"])


def test_showcase_frames_spread_over_the_contact_frames_and_fall_back_to_all():
    contact = np.array([0, 1, 1, 0, 1, 1, 1], dtype=bool)
    assert showcase_pairs(contact, 3) == [(1, 0), (4, 0), (6, 0)]
    assert showcase_pairs(contact, 10) == [(f, 0) for f in (1, 2, 4, 5, 6)]
    assert showcase_pairs(np.zeros(4, dtype=bool), 2) == [(0, 0), (3, 0)]
    assert showcase_pairs(contact, 0) == []


def test_crops_stay_inside_the_image_and_keep_its_pixels():
    image = np.arange(64 * 64 * 3, dtype=np.uint8).reshape(64, 64, 3)
    inside = crop_box(image, np.array([10.0, 20.0, 26.0, 36.0]), 16)  # a 16 px box: no resampling
    np.testing.assert_array_equal(inside, image[20:36, 10:26])
    edge = crop_box(image, np.array([60.0, 0.0, 64.0, 2.0]), 16)  # at the corner: shifted inside, at least 8 px
    np.testing.assert_array_equal(edge, np.repeat(np.repeat(image[0:8, 56:64], 2, 0), 2, 1))


def _chain() -> tuple[dict[str, dict], dict[str, dict]]:
    """A method's warmup/dynamic/evaluate manifests that read each other and the shared stages' outputs."""
    shared = {name: {"output_digest": f"{name}-1"} for name in SHARED_STAGES}
    up = {name: f"{name}-1" for name in SHARED_STAGES}
    manifests = {
        "warmup": {"output_digest": "w-1", "upstream": dict(up)},
        "dynamic": {"output_digest": "d-1", "upstream": {**up, "warmup": "w-1"}},
        "evaluate": {"output_digest": "e-1", "upstream": {**up, "dynamic": "d-1"}},
    }
    return manifests, shared


def test_a_method_is_stale_when_its_inputs_reran_after_it():
    manifests, shared = _chain()
    assert stale_reason(manifests, shared) is None
    for name in SHARED_STAGES:  # e.g. the capture regenerated at another preset in the same outputs folder
        changed = {**shared, name: {"output_digest": f"{name}-2"}}
        assert f"evaluate read another {name}" in stale_reason(manifests, changed)
    manifests["dynamic"]["output_digest"] = "d-2"  # stage two retrained, its evaluation not rerun
    assert "evaluate read another dynamic" in stale_reason(manifests, shared)
    manifests, shared = _chain()
    manifests["warmup"]["output_digest"] = "w-2"  # warm-up retrained under a stage two that was not
    assert "dynamic read another warmup" in stale_reason(manifests, shared)


def test_stale_methods_are_named_with_the_fix_and_not_tabled():
    runs = [_run("interactavatar")]
    tables = comparison_tables(
        runs,
        comparison_rows(runs),
        [],
        {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0},
        {
            "gaussian_avatars-seed2": (
                "its evaluate read another capture than the one on disk now",
                "method=gaussian_avatars seed=2",
            )
        },
    )
    assert any(
        "Left out, stale: gaussian_avatars-seed2" in n and "method=gaussian_avatars seed=2" in n
        for n in tables["notes"]
    )
    assert all(row[1] != "GAUSSIAN_AVATARS" for table in tables["tables"] for row in table["rows"])


def test_train_wall_time_leaves_out_validation():
    run = _run("interactavatar")
    assert run.train_wall_s == pytest.approx(15.0)
    run.manifests["warmup"]["metrics"]["validation_s"] = 4.0
    run.manifests["dynamic"]["metrics"]["validation_s"] = 1.5
    assert run.train_wall_s == pytest.approx(15.0 - 5.5)


def test_seeds_are_tabled_as_mean_and_spread_and_tested_with_welch():
    """Three seeds a method: a cell is the mean over the seeds' runs with their sample standard deviation, and
    the seeds table gives the difference of the means and Welch's p (scipy's, recomputed here by hand)."""
    full = [_run("interactavatar", seed=s, train_seed=s, shift=3.0) for s in range(3)]
    base = [_run("gaussian_avatars", seed=10 + s, train_seed=s) for s in range(3)]
    rows = comparison_rows(full + base)
    assert sorted(set(rows["seed"])) == [0, 1, 2]
    per_seed = np.array([lookup(comparison_rows([r]), "interactavatar", "novel_view", "full")["psnr"] for r in full])
    assert lookup(rows, "interactavatar", "novel_view", "full")["psnr"] == pytest.approx(per_seed.mean(), rel=1e-12)
    tables = comparison_tables(
        full + base, rows, [("no_pbd", 1)], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    table1 = tables["tables"][0]
    cell = next(row[2] for row in table1["rows"] if row[0] == "novel_view" and row[1] == "INTERACTAVATAR")
    assert cell == f"{per_seed.mean():.2f} ± {per_seed.std(ddof=1):.2f}"
    seeds = next(t for t in tables["tables"] if t["title"].startswith("Seeds"))
    row = next(r for r in seeds["rows"] if r[:3] == ["novel_view", "GAUSSIAN_AVATARS", "full"])
    other = np.array([lookup(comparison_rows([r]), "gaussian_avatars", "novel_view", "full")["psnr"] for r in base])
    assert row[3] == f"{per_seed.mean() - other.mean():+.2f}"
    assert row[4] == f"{max(per_seed.std(ddof=1), other.std(ddof=1)):.2f}"
    # Welch by hand: t = (m1 - m2) / sqrt(v1/n1 + v2/n2), Welch-Satterthwaite degrees of freedom
    v1, v2 = per_seed.var(ddof=1) / 3, other.var(ddof=1) / 3
    t = (per_seed.mean() - other.mean()) / np.sqrt(v1 + v2)
    dof = (v1 + v2) ** 2 / (v1**2 / 2 + v2**2 / 2)
    from scipy.stats import t as student

    assert welch_p(per_seed, other) == pytest.approx(2 * student.sf(abs(t), dof), rel=1e-9)
    assert welch_p(per_seed, other) == pytest.approx(ttest_ind(per_seed, other, equal_var=False).pvalue, rel=1e-12)
    assert row[6] == ("supported" if welch_p(per_seed, other) < 0.05 else "within the spread")
    assert any("method=no_pbd seed=1" in n for n in tables["notes"])
    assert any("Training seeds: 0, 1, 2" in n for n in tables["notes"])


def test_one_seed_has_no_spread_and_no_seeds_table():
    runs = [_run("interactavatar"), _run("gaussian_avatars", seed=1)]
    tables = comparison_tables(
        runs, comparison_rows(runs), [], {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0}
    )
    assert not any(t["title"].startswith("Seeds") for t in tables["tables"])
    assert all("±" not in cell for t in tables["tables"] for row in t["rows"] for cell in row)
    assert np.isnan(welch_p(np.array([1.0]), np.array([2.0, 3.0])))


def test_the_shared_stages_compare_checks_are_exactly_those_evaluate_reads():
    """Derived from the DAG: every stage evaluate reads that is not per-method (scene was missing, so a method
    evaluated before `stage.scene.*` changed stayed in the tables: issue 36, item 10)."""
    from pipeline.registry import load_registry

    registry = load_registry("stages")
    evaluate = registry["evaluate"]
    shared = {name for name in evaluate.inputs if not registry[name].per_method}
    assert set(SHARED_STAGES) == shared
    assert set(registry["compare"].inputs) == shared


def test_a_corrupt_method_is_named_with_the_fix_and_an_empty_comparison_is_never_published(tmp_path):
    """Issue 36 item 11: a corrupt stage two made `run.only=compare` publish a comparison with no rows, saying
    "Not evaluated yet" and calling zero methods not fair."""
    from pipeline.stage import StageContext
    from stages import REGISTRY
    from tests.conftest import compose_cfg

    shared = {}
    for name in SHARED_STAGES:
        shared[name] = tmp_path / name
        shared[name].mkdir()
        (shared[name] / "_manifest.json").write_text('{"output_digest": "x"}')
    out = tmp_path / "out"
    out.mkdir()
    ctx = StageContext(
        cfg=compose_cfg(["stage.compare.methods=[interactavatar]"]),
        subject="synth_a",
        out_dir=out,
        inputs=shared,
        method_inputs={"warmup": {}, "dynamic": {}, "evaluate": {}},
        method_problems={"interactavatar": "dynamic: gaussians.parquet does not match its manifest"},
    )
    with pytest.raises(RuntimeError, match="last comparison is kept") as err:
        REGISTRY["compare"].fn(ctx)
    assert "interactavatar is corrupted (dynamic: gaussians.parquet" in str(err.value)
    assert "`interactavatar method=interactavatar run.until=evaluate`" in str(err.value)
    assert not list(out.iterdir())  # nothing written: the runner keeps the published comparison

    runs = [_run("gaussian_avatars")]
    tables = comparison_tables(
        runs,
        comparison_rows(runs),
        [],
        {"total_wall_s": 1.0, "warmups_trained": 1, "unshared_wall_s": 2.0},
        corrupt={"interactavatar": ("dynamic: gaussians.parquet does not match its manifest", "method=interactavatar")},
    )
    assert any(
        n.startswith("Left out, corrupted: interactavatar: dynamic:") and "method=interactavatar" in n
        for n in tables["notes"]
    )
    empty = comparison_tables(
        [], comparison_rows([]), [("no_pbd", 0)], {"total_wall_s": 0.0, "warmups_trained": 0, "unshared_wall_s": 0.0}
    )
    assert any(n == "No method to compare yet." for n in empty["notes"]) and not any(
        "not fair" in n for n in empty["notes"]
    )
