"""keypoints and fit stages on the synthetic capture."""

from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

import avatar.artifacts
from data_schemas.images import read_png
from data_schemas.keypoints import KEYPOINTS
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import read_table
from pipeline.cli import run_app
from pipeline.runner import StageFailed
from stages.fit import refine_mode
from tests.conftest import compose_cfg, record_crop_reads


def test_ground_truth_source_reproduces_the_capture_and_noise_is_applied(tmp_path):
    cfg = compose_cfg(
        [
            f"paths.outputs={tmp_path}",
            "quality=smoke",
            "run.until=fit",
            "run.progress=false",
            "fit.source=ground_truth",
            "stage.keypoints.pixel_noise=2.0",
            "stage.keypoints.drop_rate=0.2",
        ]
    )
    run_app(cfg)
    root = tmp_path / "synth_a"
    report = json.loads((root / "fit" / "fit_report.json").read_text())
    assert report["source"] == "ground_truth"
    for seq in ("train", "test"):
        assert report["sequences"][seq]["mpjpe_hand_mm"] == 0.0
        fitted = read_table(root / "fit" / seq / "params.parquet", PARAMS)
        gt = read_table(root / "capture" / seq / "gt" / "params.parquet", PARAMS)
        for k in PARAM_COLUMNS:
            np.testing.assert_array_equal(fitted[k], gt[k])
    noisy = read_table(root / "keypoints" / "train" / "keypoints.parquet", KEYPOINTS)
    clean = read_table(root / "capture" / "train" / "gt" / "keypoints.parquet", KEYPOINTS)
    a = np.concatenate([np.reshape(k, (-1, 3)) for k in noisy["uvc"]])
    b = np.concatenate([np.reshape(k, (-1, 3)) for k in clean["uvc"]])
    kept = (a[:, 2] > 0) & (b[:, 2] > 0)
    assert 0.6 < kept.sum() / (b[:, 2] > 0).sum() < 0.95  # about 20% dropped
    err = np.linalg.norm(a[kept, :2] - b[kept, :2], axis=1)
    assert 1.5 < np.sqrt((err**2).mean() / 2) < 2.5  # 2 px per axis


def _refine_cfg(tmp_path, *extra: str):
    return compose_cfg(
        [
            f"paths.outputs={tmp_path}",
            "quality=smoke",
            "run.progress=false",
            "fit.source=fitted",
            "stage.fit.refine=silhouette",
            "stage.fit.refinement.iterations=3",
            "stage.fit.refinement.render_size=32",
            *extra,
        ]
    )


def _upstream_of_fit(tmp_path) -> None:
    run_app(_refine_cfg(tmp_path, "run.until=keypoints"))
    run_app(_refine_cfg(tmp_path, "run.only=frames"))


def test_refined_fit_reads_only_the_train_views_and_reports_both_fits(tmp_path, monkeypatch):
    _upstream_of_fit(tmp_path)
    root = tmp_path / "synth_a"
    read, held_out = record_crop_reads(monkeypatch, root / "capture")  # every crop the fit stage reads
    run_app(_refine_cfg(tmp_path, "run.only=fit"))
    assert read, "the refinement read no crop"
    assert not [p for p in read if set(p.parts) & set(held_out)], "the fit read the held-out camera's crops"
    report = json.loads((root / "fit" / "fit_report.json").read_text())
    assert report["refine"] == "silhouette"
    entry = report["sequences"]["train"]
    for key in ("mpjpe_hand_mm", "mpjpe_face_mm", "vertex_error_face_mm", "reprojection_px"):
        assert key in entry and key in entry["keypoint_fit"], key
    refinement = entry["refinement"]
    assert refinement["iterations"] == 3
    for stage in ("keypoint_fit", "refined"):
        views = set(refinement["silhouette_iou"][stage]["face"])
        assert views and not views & set(held_out), views
    assert len(refinement["moved_mm"]["hand"]) == len(refinement["rotated_deg"]["face"]) == 6
    assert max(refinement["moved_mm"]["face"]) > 0
    overlay = read_png(root / "fit" / "train" / "refinement.png", 3)  # keypoint fit red, refined green
    assert overlay.shape == (64, 64, 3)
    assert (overlay == (255, 64, 64)).all(-1).any() and (overlay == (64, 255, 64)).all(-1).any()


def test_empty_masks_are_one_clear_error(tmp_path, monkeypatch):
    _upstream_of_fit(tmp_path)
    frames = tmp_path / "synth_a" / "frames"

    def empty_masks(path, channels):  # a segmentation that found nothing (the artifact itself stays intact)
        image = read_png(path, channels)
        return np.zeros_like(image) if Path(path).parent.name == "mask" else image

    monkeypatch.setattr(avatar.artifacts, "read_png", empty_masks)
    with pytest.raises(StageFailed) as info:
        run_app(_refine_cfg(tmp_path, "run.only=fit"))
    message = str(info.value)
    expected = rf"{re.escape(str(frames))}/\w+/<camera>/mask/: every mask of the training cameras is empty"
    assert re.search(expected, message), message
    assert "stage.fit.refine=none" in message
    assert not (tmp_path / "synth_a" / "fit").exists()


def test_auto_refines_real_detections_seen_by_several_views():
    assert refine_mode("auto", "mediapipe", 7) == "silhouette"
    assert refine_mode("auto", "mediapipe", 2) == "silhouette"
    assert refine_mode("auto", "provided", 7) == "none"  # DECAF's masks label neck and shoulders as face
    assert refine_mode("auto", "ground_truth", 7) == "none"  # finer than the silhouettes already
    assert refine_mode("auto", "mediapipe", 1) == "none"  # one view: the outline does not fix the distance
    assert refine_mode("photometric", "ground_truth", 1) == "photometric"  # a mode set by hand is kept


def test_a_stopped_fit_resumes_after_its_last_fitted_sequence_with_the_same_bytes(tmp_path, monkeypatch):
    """A job requeued at its time limit reruns fit: it used to refit every sequence, so a --time shorter than
    the whole fit never finished it. Each fitted sequence is now kept in the stage's scratch dir; the rerun
    fits only the rest, counts the stopped run's time, and writes what an uninterrupted run writes."""
    from pipeline.manifest import read_manifest

    fit_module = importlib.import_module("stages.fit")  # the package's attribute `fit` is the Stage
    _upstream_of_fit(tmp_path)
    fit_dir = tmp_path / "synth_a" / "fit"
    real = fit_module.fit_sequence
    keypoint_fit = ("stage.fit.refine=none", "stage.fit.coarse_iterations=10", "stage.fit.fine_iterations=20")
    calls: list[int] = []

    def stopped_at_the_second_sequence(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the job's time limit")
        return real(*args, **kwargs)

    monkeypatch.setattr(fit_module, "fit_sequence", stopped_at_the_second_sequence)
    with pytest.raises(StageFailed, match="time limit"):
        run_app(_refine_cfg(tmp_path, "run.only=fit", *keypoint_fit))
    assert not fit_dir.exists()

    calls.clear()
    monkeypatch.setattr(fit_module, "fit_sequence", lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    run_app(_refine_cfg(tmp_path, "run.only=fit", *keypoint_fit))
    resumed = read_manifest(fit_dir)
    sequences = json.loads((fit_dir / "fit_report.json").read_text())["sequences"]
    assert len(calls) == len(sequences) - 1, "the sequence fitted before the stop was fitted again"
    assert resumed.timings.get("resumed_s", 0) > 0, resumed.timings

    run_app(_refine_cfg(tmp_path, "run.only=fit", "run.force=true", *keypoint_fit))  # uninterrupted
    assert read_manifest(fit_dir).outputs == resumed.outputs


def test_a_corrupt_fit_checkpoint_is_fitted_again(tmp_path, caplog):
    from stages.fit import SequenceCheckpoints

    out = tmp_path / "out" / "train"
    out.mkdir(parents=True)
    (out / "params.parquet").write_bytes(b"fitted")
    checkpoints = SequenceCheckpoints(tmp_path / "scratch")
    checkpoints.save("train", out, {"hand_fitted": True}, {"train_mpjpe_hand_mm": 1.5})
    restored = tmp_path / "restored"
    assert checkpoints.restore("train", restored / "train") == ({"hand_fitted": True}, {"train_mpjpe_hand_mm": 1.5})
    assert (restored / "train" / "params.parquet").read_bytes() == b"fitted"
    (tmp_path / "scratch" / "train" / "out" / "params.parquet").write_bytes(b"fitteD")  # bit rot
    assert checkpoints.restore("train", tmp_path / "again" / "train") is None
    assert "unusable" in caplog.text and not (tmp_path / "scratch" / "train").exists()
    assert checkpoints.restore("test", tmp_path / "again" / "test") is None  # never saved
