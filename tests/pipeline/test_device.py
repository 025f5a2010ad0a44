"""``run.device`` and ``run.precision``: resolved once on the machine that runs the stages, before any of them; the
CPU in fp32 keeps every cache key as it was; another device kind or precision is another cache entry of the stages
that compute on the device, and their manifests record where they computed."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from pipeline import device as device_module
from pipeline.cli import run_app
from pipeline.config import ConfigError, fix_command
from pipeline.device import Compute, DeviceUnavailable, cpu_name, resolve_compute, resolve_device
from pipeline.manifest import MANIFEST_NAME
from tests import toy_dag
from tests.conftest import compose_cfg, run_cli


def test_auto_takes_the_first_cuda_device_where_there_is_one_else_the_cpu() -> None:
    assert resolve_device("auto", count=0) == "cpu"
    assert resolve_device("auto", count=2) == "cuda:0"
    assert resolve_device("cuda", count=1) == "cuda:0"
    assert resolve_device("cuda:1", count=2) == "cuda:1"
    assert resolve_device("cpu", count=4) == "cpu"


def test_this_machine_without_a_gpu_resolves_auto_to_the_cpu() -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    assert resolve_compute("auto", "fp32") == Compute("cpu", "fp32")


@pytest.mark.parametrize(
    ("spec", "count", "said"),
    [
        ("cuda", 0, "run.device=cuda: this machine has no CUDA device that torch can use"),
        ("cuda:3", 0, "run.device=cuda:3: this machine has no CUDA device"),
        ("cuda:2", 2, "run.device=cuda:2: this machine has 2 CUDA device(s), cuda:0 to cuda:1"),
        ("gpu", 1, "run.device=gpu: use one of auto, cpu, cuda or cuda:N"),
        ("cuda:x", 1, "run.device=cuda:x: use one of"),
    ],
)
def test_a_device_this_machine_lacks_is_one_error_naming_the_key(spec: str, count: int, said: str) -> None:
    with pytest.raises(DeviceUnavailable) as caught:
        resolve_device(spec, count=count)
    assert str(caught.value).startswith(said)


def test_the_reference_adds_nothing_to_a_key_and_anything_else_its_kind_and_precision() -> None:
    assert Compute("cpu", "fp32").key_entries() == {}
    assert Compute("cuda:0", "fp32").key_entries() == {"run.device": "cuda"}
    assert Compute("cuda:1", "fp32").key_entries() == Compute("cuda:0", "fp32").key_entries()  # the cards share
    assert Compute("cpu", "bf16").key_entries() == {"run.precision": "bf16"}
    assert Compute("cuda:0", "bf16").key_entries() == {"run.device": "cuda", "run.precision": "bf16"}


def test_the_config_check_names_a_malformed_device_or_precision() -> None:
    from pipeline.config import validate_config
    from stages import REGISTRY

    with pytest.raises(ConfigError) as caught:
        validate_config(compose_cfg(["run.device=gpu0", "run.precision=fp16"]), REGISTRY)
    problems = caught.value.problems
    assert any(p.startswith("run.device=gpu0: use one of auto, cpu, cuda or cuda:N") for p in problems)
    assert any(p.startswith("run.precision=fp16: use fp32 (the reference) or bf16") for p in problems)


@pytest.fixture
def device_stage_b(monkeypatch: pytest.MonkeyPatch) -> None:
    """The toy DAG's stage b runs networks on the run's device, d computes there without networks; a and c run on
    the CPU."""
    stages = toy_dag.REGISTRY._stages
    monkeypatch.setitem(stages, "b", dataclasses.replace(stages["b"], device=True, precision=True))
    monkeypatch.setitem(stages, "d", dataclasses.replace(stages["d"], device=True))


def _manifest(cfg, stage: str) -> dict:
    """The toy stage's manifest as written."""
    return json.loads((Path(cfg.paths.outputs) / cfg.subject / stage / MANIFEST_NAME).read_text())


@pytest.mark.usefixtures("device_stage_b")
def test_on_the_cpu_keys_stay_as_they_were_and_the_manifest_records_the_device(toy_cfg) -> None:
    reference = {r.stage: r.action for r in run_app(toy_cfg("run.device=cpu"))}
    assert set(reference.values()) == {"run"}
    # auto on this machine is the CPU: the same keys, everything cached
    if not torch.cuda.is_available():
        assert {r.action for r in run_app(toy_cfg())} == {"cached"}
    cfg = toy_cfg()
    assert _manifest(cfg, "b")["device"] == {"kind": "cpu", "name": cpu_name(), "precision": "fp32"}
    assert "device" not in _manifest(cfg, "a") and "device" not in _manifest(cfg, "c")
    assert _manifest(cfg, "d")["device"] == {"kind": "cpu", "name": cpu_name(), "precision": "fp32"}
    assert "run.device" not in _manifest(cfg, "b")["config"]  # the key of the reference is the key it always had


@pytest.mark.usefixtures("device_stage_b")
def test_another_precision_is_another_cache_entry_of_the_stages_that_run_networks_alone(toy_cfg) -> None:
    run_app(toy_cfg("run.device=cpu"))
    reports = {r.stage: r for r in run_app(toy_cfg("run.device=cpu", "run.precision=bf16"))}
    assert reports["b"].action == "run" and "config changed: run.precision" in reports["b"].reason
    # d computes on the device without networks: the precision is not its; b wrote the same bytes (the toy does not
    # read the precision), so c, which reads it, is cached
    assert {s: reports[s].action for s in "acd"} == {"a": "cached", "c": "cached", "d": "cached"}
    assert _manifest(toy_cfg(), "b")["device"]["precision"] == "bf16"
    assert _manifest(toy_cfg(), "d")["device"]["precision"] == "fp32"


@pytest.mark.usefixtures("device_stage_b")
def test_a_gpu_is_another_cache_entry_and_its_manifest_names_the_card(toy_cfg, monkeypatch: pytest.MonkeyPatch) -> None:
    run_app(toy_cfg("run.device=cpu"))
    # a machine with one CUDA device, as far as the runner can tell
    monkeypatch.setattr(device_module, "cuda_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda index=0: "NVIDIA H100 80GB HBM3")
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device=None: 3 * 2**20)
    reports = {r.stage: r for r in run_app(toy_cfg())}  # auto: the GPU
    assert reports["b"].action == "run" and "config changed: run.device" in reports["b"].reason
    assert reports["d"].action == "run" and reports["a"].action == "cached"
    cfg = toy_cfg()
    assert _manifest(cfg, "b")["device"] == {
        "kind": "cuda",
        "name": "NVIDIA H100 80GB HBM3",
        "precision": "fp32",
        "peak_memory_mb": 3.0,
    }
    assert _manifest(cfg, "b")["config"]["run.device"] == "cuda"
    # back on the CPU: b's key is the reference's again, not the GPU's
    again = {r.stage: r for r in run_app(toy_cfg("run.device=cpu"))}
    assert again["b"].action == "run" and "config changed: run.device" in again["b"].reason


def test_a_fix_command_repeats_the_device_and_the_precision() -> None:
    cfg = compose_cfg([])
    OmegaConf.update(
        cfg, "run.overrides", ["run.device=cuda:1", "run.precision=bf16", "run.force=true", "quality=draft"]
    )
    assert fix_command(cfg, "run.only=evaluate") == (
        "interactavatar run.device=cuda:1 run.precision=bf16 quality=draft run.only=evaluate"
    )


def test_the_cli_refuses_a_gpu_this_machine_lacks_before_any_stage_runs(tmp_path) -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    done = run_cli("run.device=cuda", f"paths.outputs={tmp_path / 'out'}", "run.progress=false", timeout=300)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("interactavatar: error")]
    assert len(errors) == 1 and "run.device=cuda: this machine has no CUDA device" in done.stderr
    subject = tmp_path / "out" / "synth_a"
    assert not subject.exists() or not any(p.name != "_locks" for p in subject.iterdir())
