"""The measurement campaign (benchmarks/campaign): its queue, its result file and tables, its priority, and a runner
that resumes after a kill without redoing a finished cell or committing half of one.

The runner's cells run a stand-in for the app (``FAKE_APP``): it writes the three manifests and the metrics table a
trained and evaluated run leaves, in a second, and appends its command line to a trace file.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.campaign.cells import Cell, QueueError, load_queue
from benchmarks.campaign.priority import LOWEST_NICE
from benchmarks.campaign.results import ResultFile, aggregate
from benchmarks.campaign.runner import code_head, lock_holder
from benchmarks.campaign.tables import render
from tests.conftest import REPO, wait_for

QUEUE = """\
result = "campaign_test"
quality = "smoke"
[settings.a]
what = "ground truth"
overrides = ["fit.source=ground_truth"]
[settings.m]
what = "MediaPipe"
overrides = ["fit.source=fitted"]
[[cells]]
settings = ["a"]
methods = ["interactavatar", "gaussian_avatars"]
subjects = ["synth_a"]
seeds = [0, 1]
[[cells]]
settings = ["m"]
methods = ["interactavatar"]
subjects = ["synth_a", "synth_b"]
seeds = [0]
"""

FAKE_APP = """\
import json, os, sys, time
from pathlib import Path
import numpy as np
from data_schemas.metrics import METRICS
from data_schemas.tables import write_table
from pipeline.workspace import method_run
args = dict(a.split("=", 1) for a in sys.argv[1:])
with open(os.environ["TRACE"], "a") as trace:
    trace.write(" ".join(sys.argv[1:]) + "\\n")
if args["method"] == os.environ.get("BLOCK_METHOD") and args["seed"] == os.environ.get("BLOCK_SEED"):
    Path(os.environ["TRACE"] + ".blocked").touch()
    time.sleep(600)
if os.environ.get("FAIL_METHOD") == args["method"]:
    sys.exit(3)
run = Path(args["paths.outputs"]) / args["subject"] / "methods" / method_run(args["method"], int(args["seed"]))
level = 25.0 + int(args["seed"]) + (1.0 if args["method"] == "interactavatar" else 0.0)
for stage in ("warmup", "dynamic", "evaluate"):
    (run / stage).mkdir(parents=True, exist_ok=True)
    manifest = {"metrics": {"steps": 100, "gaussians": 500}, "timings": {"wall_s": 2.0},
                "config": {"method": {"label": args["method"]}}}
    (run / stage / "_manifest.json").write_text(json.dumps(manifest))
n = 4
write_table(run / "evaluate" / "metrics.parquet", METRICS, {
    "method": [args["method"]] * n, "split": ["novel_view", "novel_view", "self_reenact", "self_reenact"],
    "camera_id": ["c"] * n, "frame": np.arange(n, dtype=np.int32), "region": ["full"] * n,
    "contact": np.array([False, True, False, True]), "psnr": np.full(n, level, np.float32),
    "ssim": np.full(n, 0.9, np.float32), "lpips": np.full(n, 0.05, np.float32)})
"""


@pytest.fixture
def campaign(tmp_path: Path) -> dict[str, Path]:
    """A queue, a git repository holding the result file, the app's stand-in and a trace of its runs."""
    (tmp_path / "queue.toml").write_text(QUEUE)
    (tmp_path / "fake_app.py").write_text(FAKE_APP)
    repo = tmp_path / "repo"
    (repo / "results").mkdir(parents=True)
    for command in (["init", "-q"], ["config", "user.email", "t@t"], ["config", "user.name", "t"]):
        subprocess.run(["git", *command], cwd=repo, check=True)
    (repo / "README").write_text("results\n")
    subprocess.run(["git", "add", "README"], cwd=repo, check=True)
    subprocess.run(["git", "commit", "-q", "-m", "start"], cwd=repo, check=True)
    return {
        "queue": tmp_path / "queue.toml",
        "results": repo / "results" / "campaign_test.json",
        "outputs": tmp_path / "outputs",
        "app": tmp_path / "fake_app.py",
        "trace": tmp_path / "trace.txt",
        "repo": repo,
    }


def _runner(c: dict[str, Path], command: str = "run", **env: str) -> subprocess.Popen[str]:
    argv = [sys.executable, "-m", "benchmarks.campaign", command, "--queue", str(c["queue"])]
    argv += ["--results", str(c["results"]), "--outputs", str(c["outputs"]), "--code", str(REPO)]
    argv += ["--launcher", f"{sys.executable} {c['app']}"]
    full_env = {**os.environ, "TRACE": str(c["trace"]), "PYTHONPATH": str(REPO), **env}
    return subprocess.Popen(argv, cwd=REPO, env=full_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _runs(trace: Path) -> list[str]:
    """``<method> seed<k> <subject>`` of every run the stand-in started, in order."""
    out = []
    for line in trace.read_text().splitlines() if trace.is_file() else []:
        args = dict(a.split("=", 1) for a in line.split())
        out.append(f"{args['method']} seed{args['seed']} {args['subject']}")
    return out


def _commits(repo: Path) -> list[str]:
    log = subprocess.run(["git", "log", "--format=%s"], cwd=repo, capture_output=True, text=True, check=True)
    return log.stdout.splitlines()[::-1][1:]


def test_the_queue_expands_seed_by_seed_and_names_its_file_when_wrong(tmp_path: Path) -> None:
    path = tmp_path / "queue.toml"
    path.write_text(QUEUE)
    queue = load_queue(path)
    assert [c.key for c in queue.cells] == [
        "a/synth_a/interactavatar/seed0",
        "a/synth_a/gaussian_avatars/seed0",
        "a/synth_a/interactavatar/seed1",
        "a/synth_a/gaussian_avatars/seed1",
        "m/synth_a/interactavatar/seed0",
        "m/synth_b/interactavatar/seed0",
    ]
    assert queue.cells[2].run == "interactavatar-seed1" and queue.methods() == ["interactavatar", "gaussian_avatars"]
    assert queue.settings["a"].commit is None  # the newest code
    path.write_text(QUEUE.replace('what = "MediaPipe"', 'what = "MediaPipe"\ncommit = "c9a604f"'))
    assert load_queue(path).settings["m"].commit == "c9a604f"  # a bisect's: its cells run that commit's code
    path.write_text(QUEUE.replace('settings = ["m"]', 'settings = ["x"]'))
    with pytest.raises(QueueError, match=rf"{path}: cells group 2 names settings \['x'\]"):
        load_queue(path)
    path.write_text(QUEUE.replace('result = "campaign_test"\n', ""))
    with pytest.raises(QueueError, match=f"{path}: the campaign queue lacks the key 'result'"):
        load_queue(path)
    with pytest.raises(QueueError, match=f"{tmp_path / 'none.toml'}: cannot read the campaign queue"):
        load_queue(tmp_path / "none.toml")


def test_the_committed_queue_holds_the_papers_tables() -> None:
    queue = load_queue(REPO / "benchmarks" / "campaign" / "queue.toml")
    methods = {"interactavatar", "gaussian_avatars", "splatting_avatar", "no_hand_mlp", "no_interaction", "no_pbd"}
    for subject in ("synth_a", "synth_b"):
        for method in methods | {"no_patch"}:
            assert {c.seed for c in queue.cells if (c.setting, c.subject, c.method) == ("a", subject, method)} == {
                0,
                1,
                2,
            }
    assert all((REPO / "conf" / "method" / f"{m}.yaml").is_file() for m in queue.methods())


def _record(method: str, seed: int, psnr: float, commit: str) -> dict:
    metrics = [{"split": "novel_view", "region": "full", "contact": "all", "images": 4, "psnr": psnr, "ssim": 0.9}]
    metrics[0]["lpips"] = 0.05
    return {
        "setting": "a",
        "subject": "synth_a",
        "method": method,
        "seed": seed,
        "quality": "smoke",
        "commit": commit,
        "metrics": metrics,
    }


def test_rows_list_every_seed_in_order_with_its_commit_and_the_file_is_replaced_whole(tmp_path: Path) -> None:
    results = ResultFile(tmp_path / "r.json")
    for seed, psnr, commit in ((2, 27.0, "c2"), (0, 25.0, "c0"), (1, 26.0, "c1")):
        results.add(_record("interactavatar", seed, psnr, commit))
    results.add(_record("interactavatar", 1, 26.5, "c3"))  # the same cell again: replaces it
    results.save()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]  # no partial file left
    (row,) = ResultFile(tmp_path / "r.json").rows()
    assert row["seeds"] == [0, 1, 2] and row["psnr"] == [25.0, 26.5, 27.0] and row["commit"] == ["c0", "c3", "c2"]
    assert {k: row[k] for k in ("method", "subject", "setting", "split", "region", "contact")} == {
        "method": "interactavatar",
        "subject": "synth_a",
        "setting": "a",
        "split": "novel_view",
        "region": "full",
        "contact": "all",
    }
    assert ResultFile(tmp_path / "r.json").finished(Cell("a", "synth_a", "interactavatar", 2), "smoke")
    assert not ResultFile(tmp_path / "r.json").finished(Cell("a", "synth_a", "interactavatar", 2), "draft")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="bad.json: not a campaign result file"):
        ResultFile(tmp_path / "bad.json")


def test_the_tables_render_with_cells_missing(tmp_path: Path) -> None:
    path = tmp_path / "queue.toml"
    path.write_text(QUEUE)
    queue = load_queue(path)
    rows = aggregate([_record("interactavatar", 0, 25.0, "c0"), _record("interactavatar", 1, 26.0, "c0")])
    rows += aggregate([_record("gaussian_avatars", 0, 24.0, "c1")])
    page = render(queue, rows)
    assert "0 of 6" not in page and "3 of 6 cells finished" in page
    novel_view = page.split("### novel view")[1].split("###")[0]
    assert "| InteractAvatar | 2/2 | 25.50 ± 0.71 |" in novel_view
    assert "| GaussianAvatars | 1/2 | 24.00 |" in novel_view and "-1.50" in novel_view
    assert "| InteractAvatar | 0/1 | missing |" in page.split("## (m) synth_b")[1]


def test_the_runner_commits_each_cell_and_resumes_after_a_kill_without_redoing_one(campaign: dict[str, Path]) -> None:
    # the third cell (interactavatar seed 1) hangs: the runner is killed outright while it runs
    runner = _runner(campaign, BLOCK_METHOD="interactavatar", BLOCK_SEED="1")
    lock = campaign["outputs"] / "runner.lock"
    try:
        wait_for(lambda: Path(str(campaign["trace"]) + ".blocked").exists() or runner.poll() is not None, 120)
        assert runner.poll() is None, runner.communicate()[0]
        working = lock_holder(lock)  # the runner proper, in a session of its own under the command that started it
        assert working is not None
        os.kill(working, signal.SIGKILL)
    finally:
        runner.kill()
        runner.wait()
    wait_for(lambda: lock_holder(lock) is None, 30)
    subprocess.run(["pkill", "-f", str(campaign["app"])], check=False)  # the hanging stand-in: orphaned by the kill
    done = json.loads(campaign["results"].read_text())["cells"]
    assert [(c["method"], c["seed"]) for c in done] == [("interactavatar", 0), ("gaussian_avatars", 0)]
    assert _commits(campaign["repo"]) == [
        "campaign: a/synth_a/interactavatar/seed0 at smoke (code " + done[0]["commit"] + "): novel view 26.00 dB",
        "campaign: a/synth_a/gaussian_avatars/seed0 at smoke (code " + done[1]["commit"] + "): novel view 25.00 dB",
    ]
    status = subprocess.run(["git", "status", "--porcelain"], cwd=campaign["repo"], capture_output=True, text=True)
    assert status.stdout == ""  # nothing half written or left uncommitted
    # started again: the cell cut off and the rest, never a finished one
    again = _runner(campaign)
    out, _ = again.communicate(timeout=300)
    assert again.returncode == 0, out
    assert _runs(campaign["trace"]) == [
        "interactavatar seed0 synth_a",
        "gaussian_avatars seed0 synth_a",
        "interactavatar seed1 synth_a",
        "interactavatar seed1 synth_a",
        "gaussian_avatars seed1 synth_a",
        "interactavatar seed0 synth_a",
        "interactavatar seed0 synth_b",
    ]
    assert len(_commits(campaign["repo"])) == 6
    rows = json.loads(campaign["results"].read_text())["rows"]
    ia = next(
        r
        for r in rows
        if (r["setting"], r["method"], r["split"], r["contact"]) == ("a", "interactavatar", "novel_view", "all")
    )
    assert ia["seeds"] == [0, 1] and np.allclose(ia["psnr"], [26.0, 27.0])
    page = campaign["results"].with_suffix(".md").read_text()
    assert "6 of 6 cells finished" in page and "| 0/" not in page and "| 1/2 |" not in page


def test_a_failed_cell_is_said_and_skipped_at_the_same_commit(campaign: dict[str, Path]) -> None:
    runner = _runner(campaign, FAIL_METHOD="gaussian_avatars")
    out, _ = runner.communicate(timeout=300)
    assert runner.returncode == 1, out
    assert "a/synth_a/gaussian_avatars/seed0 failed (exit 3)" in out and "2 cell(s) left" in out
    failed = json.loads((campaign["outputs"] / "failed.json").read_text())
    assert sorted(failed) == ["a/synth_a/gaussian_avatars/seed0", "a/synth_a/gaussian_avatars/seed1"]
    assert Path(failed["a/synth_a/gaussian_avatars/seed0"]["log"]).is_file()
    runs = _runs(campaign["trace"])
    assert len(runs) == 6
    again = _runner(campaign)  # at the same commit: the failed cells are not tried again
    out, _ = again.communicate(timeout=300)
    assert again.returncode == 1 and "2 cell(s) left" in out and _runs(campaign["trace"]) == runs, out


def test_a_second_runner_is_refused_and_stop_ends_the_first(campaign: dict[str, Path]) -> None:
    first = _runner(campaign, BLOCK_METHOD="interactavatar", BLOCK_SEED="0")
    try:
        wait_for(lambda: Path(str(campaign["trace"]) + ".blocked").exists() or first.poll() is not None, 120)
        second = _runner(campaign)
        out, _ = second.communicate(timeout=120)
        assert second.returncode == 1 and "already works in" in out, out
        stop = _runner(campaign, "stop")
        out, _ = stop.communicate(timeout=120)
        assert stop.returncode == 0 and "stopped the runner" in out, out
        out, _ = first.communicate(timeout=60)
        assert first.returncode == 130 and "campaign: stopped" in out, out
    finally:
        first.kill()
    assert not campaign["results"].exists()  # the cell in progress was lost, nothing else
    wait_for(lambda: subprocess.run(["pgrep", "-f", str(campaign["app"])], capture_output=True).returncode != 0, 30)


LOWEST = """\
import os
from benchmarks.campaign.priority import lowest_priority
try:
    lowest_priority()
except RuntimeError as err:
    print("refused:", err)
os.setsid()
p = lowest_priority()
print(p.nice, p.idle_policy, p.lowest, "|", p.autogroup)
"""


def test_lowest_priority_refuses_a_shared_session_and_lowers_its_own() -> None:
    """In a child (never in the suite's own process, which may lead its session): refused while the child shares its
    parent's session, then, in a session of its own, nice 19, SCHED_IDLE and (where the kernel has them) its
    autogroup at nice 19."""
    done = subprocess.run([sys.executable, "-c", LOWEST], cwd=REPO, capture_output=True, text=True, check=True)
    first, second = done.stdout.splitlines()
    assert first.startswith("refused: lowest_priority() must run in a process that leads its own session"), first
    values, autogroup = second.split(" | ")
    assert values.split() == [str(LOWEST_NICE), "True", "True"], second
    if Path("/proc/self/autogroup").is_file():
        assert autogroup.endswith(f"nice {LOWEST_NICE}"), autogroup


def test_the_code_a_cell_runs_passes_over_the_campaigns_own_commits_of_results(campaign: dict[str, Path]) -> None:
    repo = campaign["repo"]

    def commit(path: str, message: str) -> str:
        (repo / path).parent.mkdir(parents=True, exist_ok=True)
        (repo / path).write_text(message)
        subprocess.run(["git", "add", path], cwd=repo, check=True)
        subprocess.run(["git", "commit", "-q", "-m", message], cwd=repo, check=True)
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True).stdout

    code = commit("avatar/model.py", "code").strip()
    commit("benchmarks/results/paper_tables.json", "a cell")
    commit("docs/results/paper_tables.md", "its page")
    assert code_head(repo) == code
    newer = commit("benchmarks/campaign/queue.toml", "more cells").strip()  # the queue is code
    assert code_head(repo) == newer
