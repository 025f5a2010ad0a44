"""The report's fit section shows the keypoint fit and its image refinement side by side (issue 34)."""

from __future__ import annotations

import json
from pathlib import Path

from stages.report import _fit_section


def _entry(hand_mm: float, face_mm: float) -> dict:
    return {
        "mpjpe_hand_mm": hand_mm,
        "mpjpe_face_mm": face_mm,
        "vertex_error_hand_mm": hand_mm,
        "vertex_error_face_mm": face_mm,
        "reprojection_px": {"hand": 4.0, "face": 5.0},
        "weak_frames": {"hand": [], "face": []},
    }


def test_refined_fit_rows_and_movement(tmp_path: Path) -> None:
    refined = {
        **_entry(7.5, 11.0),
        "keypoint_fit": _entry(11.5, 13.0),
        "refinement": {
            "iterations": 100,
            "loss": {"first": 10.0, "last": 5.0},
            "silhouette_iou": {
                "keypoint_fit": {"face": {"cam00": 0.8, "cam01": 0.6}, "hand": {"cam00": 0.7}},
                "refined": {"face": {"cam00": 0.9, "cam01": 0.9}, "hand": {"cam00": 0.85}},
            },
            "moved_mm": {"face": [1.0, 3.0], "hand": [2.0, 6.0]},
            "rotated_deg": {"face": [0.5, 1.5], "hand": [2.0, 4.0]},
            "unseen_frames": {"face": [], "hand": []},
        },
    }
    (tmp_path / "fit_report.json").write_text(
        json.dumps({"source": "fitted", "refine": "silhouette", "train_views": 7, "sequences": {"train": refined}})
    )
    html = _fit_section(tmp_path)
    assert "<td>train (keypoint fit)</td><td>11.5</td>" in html
    assert "<td>train (refined: silhouette)</td><td>7.5</td>" in html
    assert "<td>0.7 → 0.9</td><td>0.7 → 0.85</td><td>2 / 3</td><td>4 / 6</td><td>1.5</td><td>4</td>" in html


def test_unrefined_fit_has_one_row_per_sequence(tmp_path: Path) -> None:
    (tmp_path / "fit_report.json").write_text(
        json.dumps({"source": "fitted", "refine": "none", "train_views": 7, "sequences": {"train": _entry(11.5, 13.0)}})
    )
    html = _fit_section(tmp_path)
    assert "<td>train</td><td>11.5</td>" in html and "refined" not in html
