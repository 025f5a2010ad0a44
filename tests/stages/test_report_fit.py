"""The report's fit section shows the keypoint fit and its image refinement side by side; the fitted (and, with
ground truth, the true) meshes' outlines over a training crop and the rig always; the contact sheet wraps."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import cv2
import numpy as np
from omegaconf import OmegaConf

from avatar.synthetic.rig import look_at
from avatar.templates import procedural_hand, procedural_head
from data_schemas.cameras import Camera
from data_schemas.frames import rgb_path
from data_schemas.images import write_png
from data_schemas.params import PARAM_COLUMNS
from reporting.capture import contact_sheet_section, posed_meshes, rig_section
from reporting.fit import FITTED_RGB, OUTLINE_MIN_PX, TRUE_RGB, fit_section, outlines_section
from reporting.html import SHEET_MAX_PX, contact_sheet, page

REPO = Path(__file__).resolve().parents[2]


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
    html = fit_section(tmp_path)
    assert "<td>train (keypoint fit)</td><td>11.5</td>" in html
    assert "<td>train (refined: silhouette)</td><td>7.5</td>" in html
    assert "<td>0.7 → 0.9</td><td>0.7 → 0.85</td><td>2 / 3</td><td>4 / 6</td><td>1.5</td><td>4</td>" in html


def test_unrefined_fit_has_one_row_per_sequence(tmp_path: Path) -> None:
    (tmp_path / "fit_report.json").write_text(
        json.dumps({"source": "fitted", "refine": "none", "train_views": 7, "sequences": {"train": _entry(11.5, 13.0)}})
    )
    html = fit_section(tmp_path)
    assert "<td>train</td><td>11.5</td>" in html and "refined" not in html


HEAD, HAND = procedural_head(), procedural_hand()
SEQ, FRAME, CROP_PX = "train", 0, 64


def _params(shift_m: float = 0.0) -> dict[str, np.ndarray]:
    """One frame of rest-pose parameters: the head at the origin, the hand raised in front of it; the head moved
    ``shift_m`` to the right."""
    widths = {"flame_shape": 10, "flame_expression": 10, "mano_shape": 10, "mano_hand_pose": 45, "flame_eye_pose": 6}
    params = {k: np.zeros((1, widths.get(k, 3)), np.float32) for k in PARAM_COLUMNS}
    params["flame_transl"][0] = (shift_m, 0.0, 0.0)
    params["mano_transl"][0] = (-0.05, -0.05, 0.12)
    params["mano_global_orient"][0] = (0.0, 0.0, 1.5)
    return params


def _cameras(count: int = 8) -> list[Camera]:
    """``count`` cameras on an arc 0.8 m in front of the origin, looking at it; the fourth held out."""
    K = np.array([[90.0, 0.0, CROP_PX / 2], [0.0, 90.0, CROP_PX / 2], [0.0, 0.0, 1.0]])
    return [
        Camera(
            f"cam{i:02d}",
            CROP_PX,
            CROP_PX,
            K,
            look_at(0.8 * np.array([np.sin(a), 0.0, np.cos(a)]), np.zeros(3), np.array([0.0, 1.0, 0.0])),
            np.zeros(5),
            "test" if i == 3 else "train",
        )
        for i, a in enumerate(np.linspace(-1.2, 1.2, count))
    ]


def _frames(root: Path, cameras: list[Camera]) -> dict[str, list]:
    """A grey crop of FRAME per camera under ``root`` (the frames stage's layout) and the index rows the report
    reads (the crop is the whole image)."""
    for cam in cameras:
        write_png(rgb_path(root, SEQ, cam.camera_id, FRAME), np.full((CROP_PX, CROP_PX, 3), 128, np.uint8))
    return {
        "sequence": [SEQ] * len(cameras),
        "camera_id": [c.camera_id for c in cameras],
        "frame": [FRAME] * len(cameras),
        "K": [c.K.reshape(-1) for c in cameras],
    }


def _png_pixels(html: str, alt: str) -> np.ndarray:
    """The (H, W, 3) RGB pixels of the page's base64 PNG described by ``alt``."""
    found = re.search(f"alt='{alt}' src='data:image/png;base64,([^']*)'", html)
    assert found, alt
    image = cv2.imdecode(np.frombuffer(base64.b64decode(found.group(1)), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image[..., ::-1]


def _has(image: np.ndarray, rgb: tuple[int, int, int]) -> bool:
    return bool((image == rgb).all(-1).any())


def test_the_fitted_and_true_outlines_and_the_rig(tmp_path: Path) -> None:
    """With ground truth: the fitted (red) and true (blue) outlines over the first training camera's crop,
    upscaled for thin lines, captioned; the rig of every camera around the fitted meshes."""
    cameras = _cameras()
    index = _frames(tmp_path, cameras)
    meshes = (HEAD, HAND, True)
    shown = (SEQ, FRAME, "middle frame")
    html = outlines_section(tmp_path, index, cameras[0], shown, _params(), _params(0.01), meshes, "fitted")
    assert "the fitted meshes&#x27; outlines (red) over the true meshes&#x27; outlines (blue" in html
    image = _png_pixels(html, "fitted mesh outlines")
    assert image.shape[0] >= OUTLINE_MIN_PX and _has(image, FITTED_RGB) and _has(image, TRUE_RGB)

    rig = rig_section(cameras, posed_meshes(_params(), FRAME, HEAD, HAND, True), SEQ, FRAME)
    assert "blue the training cameras, orange the held-out one(s)" in rig
    assert _png_pixels(rig, "the capture rig").shape[1] <= SHEET_MAX_PX


def test_without_ground_truth_only_the_fitted_outlines(tmp_path: Path) -> None:
    cameras = _cameras(2)
    index = _frames(tmp_path, cameras)
    html = outlines_section(
        tmp_path, index, cameras[0], (SEQ, FRAME, "middle frame"), _params(), None, (HEAD, HAND, False), "fitted"
    )
    image = _png_pixels(html, "fitted mesh outlines")
    assert "outlines (red)" in html and "true" not in html
    assert _has(image, FITTED_RGB) and not _has(image, TRUE_RGB)


def test_the_contact_sheet_wraps_into_rows_no_wider_than_the_page(tmp_path: Path) -> None:
    """8 cameras at the configured thumbnail size: rows of at most 4, no wider than SHEET_MAX_PX; the page's CSS
    shrinks any wider image too."""
    px = int(OmegaConf.select(OmegaConf.load(REPO / "conf" / "stage" / "report.yaml"), "thumbnail_px"))
    cameras = _cameras()
    _frames(tmp_path, cameras)
    sheet = contact_sheet(tmp_path, SEQ, [c.camera_id for c in cameras], FRAME, px)
    html = contact_sheet_section(SEQ, FRAME, "middle frame", sheet, cameras)
    image = _png_pixels(html, "contact sheet")
    assert image.shape[1] <= SHEET_MAX_PX and image.shape[0] >= 2 * px  # two rows of four
    assert "Row by row: cam00 (training camera)" in html and "cam03 (held-out camera)" in html
    assert "img,video{max-width:100%;height:auto}" in page([html])
