"""The pbd stage on a small synthetic capture: every source, the shared loader, determinism, bad input.

(Non-finite parameters never reach the stage: the table layer refuses them when written and read;
the solver itself names the frame, tests/pbd/test_solver.py.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from avatar.artifacts.motion import posed_sequence, templates
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.tables import read_table
from pipeline.cli import run_app
from tests.conftest import compose_cfg

SMALL = [
    "quality=smoke",
    "quality.capture_size=48",
    "stage.capture.num_cameras=3",
    "fit.source=ground_truth",
    "run.progress=false",
]


def _run(out: Path, *extra: str) -> dict:
    until = [] if any(e.startswith("run.only") for e in extra) else ["run.until=pbd"]
    cfg = compose_cfg([f"paths.outputs={out}", *SMALL, *until, *extra])
    run_app(cfg)
    return json.loads((out / "synth_a" / "pbd" / "_manifest.json").read_text())


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("pbd")
    return out, _run(out)


def test_simulate_removes_penetration_and_beats_zero_offsets(simulated: tuple[Path, dict]) -> None:
    out, manifest = simulated
    root = out / "synth_a"
    report = json.loads((root / "pbd" / "pbd_report.json").read_text())
    metrics = manifest["metrics"]
    assert report["source"] == "simulate" and report["stiffness"] == "template"
    assert metrics["simulated_frames"] > 0
    for seq in ("train", "test"):
        gt = read_table(root / "capture" / seq / "gt" / "deform.parquet", DEFORM)
        deform = read_table(root / "pbd" / seq / "deform.parquet", DEFORM)
        contacts = read_table(root / "pbd" / seq / "contacts.parquet", CONTACTS)
        frames = report["sequences"][seq]["frames"]
        for t, row in enumerate(frames):
            if gt["contact"][t]:  # every contact frame of the capture is simulated, and leaves < 0.3 mm
                assert row["simulated"] and row["penetration_max_mm"] < 0.3, row
                assert contacts["face"][t].any() and contacts["hand"][t].any()
            if not row["simulated"]:
                assert not np.any(deform["offsets"][t])
        assert np.array_equal(deform["contact"], gt["contact"])
    assert metrics["penetration_max_mm"] < 0.3
    assert metrics["gt_vertex_error_mm"] < metrics["zero_offset_error_mm"]


def test_shared_loader_adds_the_offsets_to_the_face_only(simulated: tuple[Path, dict]) -> None:
    out, _ = simulated
    root = out / "synth_a"
    cfg = compose_cfg([f"paths.outputs={out}", *SMALL])
    plain = posed_sequence(root / "fit", "train", cfg, None).meshes
    dented = posed_sequence(root / "fit", "train", cfg, root / "pbd").meshes
    num_face = templates(cfg.model)[0].num_vertices
    offsets = np.asarray(read_table(root / "pbd" / "train" / "deform.parquet", DEFORM)["offsets"])
    np.testing.assert_allclose(
        (dented.vertices - plain.vertices)[:, :num_face].numpy(), offsets.reshape(len(offsets), num_face, 3), atol=1e-6
    )
    assert np.array_equal(dented.vertices[:, num_face:].numpy(), plain.vertices[:, num_face:].numpy())


def test_rerun_is_byte_identical_and_other_sources(simulated: tuple[Path, dict]) -> None:
    out, first = simulated
    again = _run(out, "run.only=pbd", "run.force=true")
    assert again["outputs"] == first["outputs"]
    truth = _run(out, "run.only=pbd", "stage.pbd.source=ground_truth")
    assert truth["metrics"]["gt_vertex_error_mm"] == 0.0 and truth["metrics"]["simulated_frames"] == 0
    none = _run(out, "run.only=pbd", "stage.pbd.source=none")
    assert none["metrics"]["gt_vertex_error_mm"] == none["metrics"]["zero_offset_error_mm"] > 0
    zero = read_table(out / "synth_a" / "pbd" / "train" / "deform.parquet", DEFORM)
    assert not np.any(zero["offsets"]) and zero["contact"].any()  # contact is still flagged
    with pytest.raises(Exception, match="source=provided needs deformations shipped"):
        _run(out, "run.only=pbd", "stage.pbd.source=provided")
    with pytest.raises(Exception, match="stage.pbd.source='bogus'"):
        _run(out, "run.only=pbd", "stage.pbd.source=bogus")
