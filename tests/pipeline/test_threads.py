"""``run.threads`` and how idle threads wait: a job computes on the cores it may use (its affinity, its cgroup's CPU
quota, the environment's OMP_NUM_THREADS, its share of a local batch), never on a count that follows the machine's
load; the count is in no cache key and the manifest records it; the entry point lets idle OpenMP threads sleep
before anything loads the OpenMP runtime."""

from __future__ import annotations

import os
import sys
import types
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import torch
from omegaconf import DictConfig, OmegaConf

from pipeline import launch
from pipeline import threads as threads_module
from pipeline.batch import jobs_at_once, share_threads
from pipeline.cli import run_app
from pipeline.config import ConfigError, key_config, validate_config
from pipeline.manifest import read_manifest
from pipeline.threads import (
    cgroup_quota,
    choose_threads,
    env_threads,
    quota_cores,
    threads_problem,
    usable_cores,
    use_threads,
)
from stages import REGISTRY
from tests.conftest import compose_cfg


@pytest.fixture(autouse=True)
def _torch_threads_restored() -> Iterator[None]:
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize(
    ("setting", "cores", "environ", "jobs", "expected"),
    [
        ("auto", 2, None, 1, 2),  # the cores this process may use
        ("auto", 64, None, 1, 64),
        ("auto", 1, None, 1, 1),
        ("auto", 2, 1, 1, 1),  # the environment's count wins (a launcher that shares the cores out, the user)
        ("auto", 2, 8, 1, 8),
        ("auto", 8, None, 2, 4),  # a local batch running two jobs at once: each its share
        ("auto", 2, None, 3, 1),  # more jobs than cores: one thread each, never none
        ("auto", 2, 4, 2, 4),  # OMP_NUM_THREADS is each process's own, as OpenMP reads it: not shared again
        ("3", 2, None, 1, 3),  # a number as given, whatever the machine
        (1, 64, 8, 4, 1),
    ],
)
def test_the_thread_count_follows_the_cores_the_environment_and_the_batch(
    setting: object, cores: int, environ: int | None, jobs: int, expected: int
) -> None:
    assert choose_threads(setting, cores, environ, jobs) == expected


@pytest.mark.parametrize("setting", ["0", "-2", "many", "1.5", ""])
def test_a_setting_that_is_neither_auto_nor_a_count_is_refused_naming_the_key(setting: str) -> None:
    assert threads_problem(setting) == f"run.threads={setting}: use auto or a number of threads, e.g. run.threads=1"
    with pytest.raises(ValueError, match="run.threads"):
        choose_threads(setting, 2)
    with pytest.raises(ConfigError, match=r"run\.threads="):
        validate_config(compose_cfg([f"run.threads={setting or 'null'}"]), REGISTRY)


@pytest.mark.parametrize(
    ("value", "expected"), [("4", 4), ("4,2", 4), (" 3 ", 3), ("", None), ("0", None), ("x", None)]
)
def test_the_environment_s_count_is_omp_num_threads_first_level(value: str, expected: int | None) -> None:
    assert env_threads({"OMP_NUM_THREADS": value}) == expected
    assert env_threads({}) is None


def test_the_cores_are_the_affinity_within_the_cgroup_quota_rounded_down() -> None:
    assert usable_cores(affinity=2, quota=None) == 2
    assert usable_cores(affinity=64, quota=2.0) == 2  # a container limited to 2 CPUs on a big host
    assert usable_cores(affinity=64, quota=2.5) == 2
    assert usable_cores(affinity=2, quota=8.0) == 2
    assert usable_cores(affinity=4, quota=0.5) == 1
    assert quota_cores("max", "100000") is None and quota_cores("-1", "100000") is None
    assert quota_cores("150000", "100000") == 1.5


def _cgroup(tmp_path: Path, line: str, files: dict[str, str]) -> tuple[Path, Path]:
    tmp_path.mkdir()
    proc = tmp_path / "proc_cgroup"
    proc.write_text(line + "\n")
    root = tmp_path / "sys_fs_cgroup"
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return proc, root


def test_the_cgroup_quota_is_the_smallest_on_the_path_to_the_root_v2_and_v1(tmp_path: Path) -> None:
    proc, root = _cgroup(
        tmp_path / "v2", "0::/jobs/one", {"cpu.max": "max 100000\n", "jobs/cpu.max": "300000 100000\n"}
    )
    assert cgroup_quota(proc, root) == 3.0
    proc, root = _cgroup(
        tmp_path / "v1",
        "4:memory:/x\n3:cpu,cpuacct:/x",
        {"cpu,cpuacct/x/cpu.cfs_quota_us": "50000\n", "cpu,cpuacct/x/cpu.cfs_period_us": "100000\n"},
    )
    assert cgroup_quota(proc, root) == 0.5
    proc, root = _cgroup(tmp_path / "none", "0::/", {"cpu.max": "max 100000\n"})
    assert cgroup_quota(proc, root) is None
    assert cgroup_quota(tmp_path / "missing", root) is None


def test_auto_is_the_same_on_a_busy_machine_as_on_an_idle_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """The count changes the rounding of torch's sums: one that followed the load would make a stage forced twice
    write other bytes when something else ran meanwhile."""
    counts = []
    for load in ((0.0, 0.0, 0.0), (40.0, 40.0, 40.0)):
        monkeypatch.setattr(os, "getloadavg", lambda load=load: load)
        counts.append(use_threads("auto"))
    assert counts[0] == counts[1] == choose_threads("auto", usable_cores(), env_threads()) == torch.get_num_threads()


def test_a_job_computes_on_run_threads_which_is_in_no_key_and_which_its_manifests_record(
    toy_cfg: Callable[..., DictConfig],
) -> None:
    first = run_app(toy_cfg("run.threads=1"), job=True)
    assert {r.action for r in first} == {"run"} and torch.get_num_threads() == 1
    manifest = read_manifest(Path(toy_cfg().paths.outputs) / "synth_a" / "a")
    assert manifest is not None and manifest.threads == 1
    again = run_app(toy_cfg("run.threads=2"), job=True)
    assert {r.action for r in again} == {"cached"} and torch.get_num_threads() == 2
    torch.set_num_threads(3)
    run_app(toy_cfg("run.threads=1"))  # in a caller's own process (a test, a benchmark): its count is kept
    assert torch.get_num_threads() == 3


def test_no_stage_s_key_holds_the_thread_count() -> None:
    one, two = compose_cfg(["run.threads=1"]), compose_cfg(["run.threads=2"])
    assert all(key_config(one, s) == key_config(two, s) for s in REGISTRY)


def test_the_entry_point_lets_idle_threads_sleep_before_it_loads_the_app(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    seen: dict[str, str | None] = {}
    app = types.ModuleType("pipeline.cli")
    app.main = lambda: seen.setdefault("policy", os.environ.get("OMP_WAIT_POLICY"))  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pipeline.cli", app)
    launch.main()
    assert seen == {"policy": "PASSIVE"}
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # one the user set is kept
    threads_module.wait_passively()
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"


def _launcher(target: str, **fields: object) -> DictConfig:
    return OmegaConf.create({"_target_": target, **fields})


def test_a_batch_knows_how_many_of_its_jobs_run_at_once_on_this_machine() -> None:
    joblib = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    assert jobs_at_once(_launcher(joblib, n_jobs=2), 5, cores=2) == 2
    assert jobs_at_once(_launcher(joblib, n_jobs=2), 1, cores=2) == 1
    assert jobs_at_once(_launcher(joblib, n_jobs=-1), 5, cores=4) == 4  # joblib's convention: every core
    assert jobs_at_once(_launcher(joblib, n_jobs=-2), 5, cores=4) == 3  # all but one
    assert jobs_at_once(_launcher("hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"), 3, 2) == 3
    assert jobs_at_once(_launcher("hydra._internal.core_plugins.basic_launcher.BasicLauncher"), 3, 2) == 1
    assert jobs_at_once(_launcher("hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"), 3, 2) == 0


def test_a_local_batch_gives_each_job_with_auto_its_share_of_the_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(threads_module, "usable_cores", lambda: 4)
    monkeypatch.setattr("pipeline.batch.usable_cores", lambda: 4)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    jobs = [OmegaConf.create({"run": {"threads": "auto"}}) for _ in range(3)] + [
        OmegaConf.create({"run": {"threads": "3"}})  # the user's own count is kept
    ]
    local = _launcher("hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher")
    assert share_threads(jobs, local) == 1
    assert [str(j.run.threads) for j in jobs] == ["1", "1", "1", "3"]
    pair = [OmegaConf.create({"run": {"threads": "auto"}}) for _ in range(2)]
    assert share_threads(pair, local) == 2 and [str(j.run.threads) for j in pair] == ["2", "2"]
    remote = [OmegaConf.create({"run": {"threads": "auto"}}) for _ in range(3)]
    slurm = _launcher("hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher")
    assert share_threads(remote, slurm) is None and {str(j.run.threads) for j in remote} == {"auto"}
