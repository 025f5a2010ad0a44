"""capture + frames on a folder dataset: a good capture imports; every bad input is one clear error."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from avatar.calibration.undistort import Undistorter
from data_schemas.cameras import Camera, read_cameras, write_cameras
from data_schemas.capture import CaptureIndex, mask_path, video_path
from data_schemas.frames import FRAMES_INDEX, UNOBSERVED, crop_mask_path, rgb_path
from data_schemas.images import read_png, write_png
from data_schemas.tables import read_table
from data_schemas.video import read_video, write_video
from pipeline.cli import run_app
from pipeline.config import ConfigError
from pipeline.runner import StageFailed
from tests.conftest import compose_cfg

SIZE, FRAMES = 48, 3


def _camera(i: int) -> Camera:
    T = np.eye(4)
    T[:3, 3] = [0.01 * i, 0, 0.8]
    K = np.array([[60.0, 0, SIZE / 2], [0, 60.0, SIZE / 2], [0, 0, 1]])
    return Camera(f"cam{i:02d}", SIZE, SIZE, K, T, np.zeros(5), "test" if i == 2 else "train")


def _frames(shift: int, n: int = FRAMES) -> np.ndarray:
    video = np.full((n, SIZE, SIZE, 3), 90, np.uint8)
    for t in range(n):
        video[t, 12 + t : 30 + t, 10 + shift : 34 + shift] = (210, 160, 130)
    return video


def make_capture(root: Path, masks: bool = False) -> Path:
    subject = root / "alice"
    cams = [_camera(i) for i in range(3)]
    write_cameras(subject / "cameras.parquet", cams)
    for i, cam in enumerate(cams):
        write_video(video_path(subject, "train", cam.camera_id), _frames(i), 25.0)
        if masks:
            for t in range(FRAMES):
                lab = np.zeros((SIZE, SIZE), np.uint8)
                lab[12 + t : 30 + t, 10 + i : 34 + i] = 1
                write_png(mask_path(subject, "train", cam.camera_id, t), lab)
    return subject


def _cfg(tmp_path: Path, *extra: str):
    return compose_cfg(
        [
            "dataset=folder",
            f"dataset.root={tmp_path / 'data'}",
            "subject=alice",
            f"paths.outputs={tmp_path / 'out'}",
            "run.progress=false",
            "run.until=frames",
            "stage.frames.segmenter=key",  # the toy captures' plain background (MediaPipe is dataset=folder's default)
            *extra,
        ]
    )


@pytest.mark.parametrize("masks", [False, True], ids=["keyed", "capture-masks"])
def test_folder_capture_imports_and_crops(tmp_path, masks):
    make_capture(tmp_path / "data", masks=masks)
    reports = run_app(_cfg(tmp_path))
    assert [r.action for r in reports] == ["run", "run"]
    out = tmp_path / "out" / "alice"
    index = read_table(out / "frames" / "index.parquet", FRAMES_INDEX)
    assert len(index["frame"]) == 3 * FRAMES
    assert set(index["split"]) == {"train", "test"}
    assert all(f > 0.05 for f in index["foreground_fraction"])
    assert index["face_visible"].all() == masks  # keyed masks do not know the part
    assert not index["hand_visible"].any()


def _expect_capture_error(tmp_path: Path, fragment: str) -> None:
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path))
    assert fragment in str(info.value)
    assert not (tmp_path / "out" / "alice" / "capture").exists(), "half-written capture left behind"


def test_missing_video_names_the_camera_and_fix(tmp_path):
    subject = make_capture(tmp_path / "data")
    video_path(subject, "train", "cam01").unlink()
    _expect_capture_error(tmp_path, "cam01.mp4: camera 'cam01' in")
    with pytest.raises(StageFailed, match="add the video or remove the camera's row"):
        run_app(_cfg(tmp_path))


def test_video_without_camera(tmp_path):
    subject = make_capture(tmp_path / "data")
    shutil.copy(video_path(subject, "train", "cam00"), video_path(subject, "train", "cam09"))
    _expect_capture_error(tmp_path, "cam09.mp4: video has no camera 'cam09'")


def test_views_that_disagree_on_frame_count(tmp_path):
    subject = make_capture(tmp_path / "data")
    write_video(video_path(subject, "train", "cam02"), _frames(2, n=FRAMES + 2), 25.0)
    _expect_capture_error(tmp_path, "views disagree on frame count")


def test_corrupt_video(tmp_path):
    subject = make_capture(tmp_path / "data")
    video_path(subject, "train", "cam00").write_bytes(b"\x00not a video" * 10)
    _expect_capture_error(tmp_path, "cam00.mp4: no decodable frames")


def test_singular_intrinsics(tmp_path):
    subject = make_capture(tmp_path / "data")
    table = pq.read_table(subject / "cameras.parquet")
    k = table.column("K").to_pylist()
    k[1] = [0.0] * 9
    import pyarrow as pa

    idx = table.schema.get_field_index("K")
    table = table.set_column(idx, table.schema.field("K"), pa.array(k, type=table.schema.field("K").type))
    pq.write_table(table, subject / "cameras.parquet")
    _expect_capture_error(tmp_path, "camera 'cam01': K is singular")


def test_empty_mask_is_named(tmp_path):
    subject = make_capture(tmp_path / "data", masks=True)
    write_png(mask_path(subject, "train", "cam01", 2), np.zeros((SIZE, SIZE), np.uint8))
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path))
    assert "masks/cam01/000002.png: empty foreground mask in frame 2" in str(info.value)
    assert not (tmp_path / "out" / "alice" / "frames").exists()


def test_missing_capture_folder_is_refused_before_any_stage(tmp_path):
    for extra in ([], ["run.dry=true"]):  # a dry run used to plan every stage as "would run"
        with pytest.raises(ConfigError, match="capture folder missing; set dataset.root"):
            run_app(_cfg(tmp_path, *extra))
    assert not (tmp_path / "out" / "alice").exists()


def _zero_middle_of_mdat(path: Path) -> None:
    """Overwrite the middle half of an mp4's media data (its index, the moov box, stays intact)."""
    data = bytearray(path.read_bytes())
    box = data.find(b"mdat") - 4
    size = int.from_bytes(data[box : box + 4], "big")
    start, end = box + 8 + (size - 8) // 4, box + 8 + 3 * (size - 8) // 4
    data[start:end] = bytes(end - start)
    path.write_bytes(bytes(data))


def test_video_with_a_corrupt_middle_is_called_damaged(tmp_path):
    subject = make_capture(tmp_path / "data")
    for i in range(3):  # long enough that a zeroed stretch stops the decoder (3 frames decode as garbage)
        write_video(video_path(subject, "train", f"cam{i:02d}"), _frames(i, n=9), 25.0)
    _zero_middle_of_mdat(video_path(subject, "train", "cam01"))
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path))
    message = str(info.value)
    assert re.search(
        r"cam01\.mp4: the file is damaged: only \d of the 9 frames its container announces decode", message
    ), message
    assert "re-export or re-encode it" in message and "views disagree" not in message
    assert not (tmp_path / "out" / "alice" / "capture").exists()


def test_empty_subject_folder_names_the_layout(tmp_path):
    (tmp_path / "data" / "alice").mkdir(parents=True)
    _expect_capture_error(tmp_path, "alice: capture folder is empty; put cameras.parquet, one row per camera")
    with pytest.raises(StageFailed, match=r"<sequence>/videos/<camera_id>\.mp4"):
        run_app(_cfg(tmp_path))


def test_missing_cameras_table_names_the_file_and_fix(tmp_path):
    subject = make_capture(tmp_path / "data")
    (subject / "cameras.parquet").unlink()
    _expect_capture_error(tmp_path, "alice: camera calibration missing; add cameras.parquet, one row")
    with pytest.raises(StageFailed, match="a COLMAP sparse model or a nerfstudio transforms.json"):
        run_app(_cfg(tmp_path))


def test_replacing_a_source_video_reruns_the_capture_and_everything_below(tmp_path):
    """Issue 9, case 2: the capture's key covers the source files' content, not only the config."""
    subject = make_capture(tmp_path / "data")
    reasons = lambda reports: {r.stage: (r.action, r.reason) for r in reports}  # noqa: E731
    run_app(_cfg(tmp_path))
    assert {a for a, _ in reasons(run_app(_cfg(tmp_path))).values()} == {"cached"}
    write_video(video_path(subject, "train", "cam02"), _frames(5), 25.0)  # another take of the same camera
    after = reasons(run_app(_cfg(tmp_path)))
    assert after["capture"] == ("run", "source changed: train/videos/cam02.mp4")
    assert after["frames"] == ("run", "upstream changed: capture")


def test_published_capture_shares_no_storage_with_the_source(tmp_path):
    """Issue 9, case 2: editing a source file in place never changes a published artifact."""
    subject = make_capture(tmp_path / "data")
    run_app(_cfg(tmp_path, "run.until=capture"))
    source = video_path(subject, "train", "cam01")
    published = video_path(tmp_path / "out" / "alice" / "capture", "train", "cam01")
    before = published.read_bytes()
    assert source.stat().st_ino != published.stat().st_ino
    with open(source, "r+b") as f:  # in place: same inode, and a hard link would see it
        f.seek(100)
        f.write(b"\0" * 64)
    assert published.read_bytes() == before
    reports = {r.stage: (r.action, r.reason) for r in run_app(_cfg(tmp_path, "run.until=capture"))}
    assert reports["capture"] == ("run", "source changed: train/videos/cam01.mp4")


def _colmap_capture(root: Path, distorted: str = "cam01") -> Path:
    """The capture of :func:`make_capture` calibrated by a COLMAP model in COLMAP's layout (sparse/0),
    in half-metre units; camera ``distorted`` has OpenCV distortion."""
    import pycolmap

    subject = make_capture(root)
    (subject / "cameras.parquet").unlink()
    rec = pycolmap.Reconstruction()
    for i in range(3):
        cam = _camera(i)
        camera = pycolmap.Camera.create_from_model_name(i + 1, "OPENCV", 60.0, SIZE, SIZE)
        k1 = -0.8 if cam.camera_id == distorted else 0.0
        camera.params = [60.0, 60.0, SIZE / 2 + 0.5, SIZE / 2 + 0.5, k1, 0.0, 0.0, 0.0]
        rec.add_camera_with_trivial_rig(camera)
        pose = pycolmap.Rigid3d(
            rotation=pycolmap.Rotation3d(np.array([0.0, 0.0, 0.0, 1.0])), translation=cam.world_to_cam[:3, 3] / 0.5
        )
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{cam.camera_id}.png", camera_id=i + 1, image_id=i + 1), pose
        )
    (subject / "sparse" / "0").mkdir(parents=True)
    rec.write(str(subject / "sparse" / "0"))
    return subject


def test_colmap_calibration_is_scaled_undistorted_once_and_recorded(tmp_path):
    subject = _colmap_capture(tmp_path / "data")
    reports = run_app(_cfg(tmp_path, "dataset.calibration_scale_m=0.5", "dataset.test_cameras=[cam02]"))
    assert [r.action for r in reports] == ["run", "run"]
    capture = tmp_path / "out" / "alice" / "capture"
    cameras = {c.camera_id: c for c in read_cameras(capture / "cameras.parquet")}
    for i in range(3):
        expected = _camera(i)
        np.testing.assert_allclose(cameras[expected.camera_id].world_to_cam, expected.world_to_cam, atol=1e-12)
        np.testing.assert_allclose(cameras[expected.camera_id].K, expected.K, atol=1e-12)  # the 0.5 px shift
        assert not cameras[expected.camera_id].dist.any()  # later stages see pinhole cameras
    assert [cameras[c].split for c in sorted(cameras)] == ["train", "train", "test"]
    record = json.loads((capture / "calibration.json").read_text())
    assert record["source"].endswith("sparse/0") and record["scale_m"] == 0.5
    assert list(record["undistorted"]) == ["cam01"] and record["undistorted"]["cam01"][0] == -0.8
    for cam_id in ("cam00", "cam02"):  # undistorted cameras are copied as they are
        assert video_path(capture, "train", cam_id).read_bytes() == video_path(subject, "train", cam_id).read_bytes()
    # The distorted one is re-encoded through its own undistortion (tested against projections in
    # tests/calibration), equal up to the video codec's rounding.
    assert video_path(capture, "train", "cam01").read_bytes() != video_path(subject, "train", "cam01").read_bytes()
    source = read_video(video_path(subject, "train", "cam01"))
    imported = read_video(video_path(capture, "train", "cam01"))
    dist = np.array([-0.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    expected = np.stack([Undistorter(_camera(1).K, dist, SIZE, SIZE).image(f) for f in source])
    # Compared on the patch's silhouette: the codec's rounding of a 48 px video is larger than colour tolerances.
    patch = lambda v: np.abs(v.astype(int) - 90).sum(-1) > 115  # noqa: E731
    iou = lambda a, b: (patch(a) & patch(b)).sum() / (patch(a) | patch(b)).sum()  # noqa: E731
    assert iou(imported, expected) > 0.95 > iou(imported, source)


def test_colmap_image_that_matches_no_video_names_the_model_and_camera(tmp_path):
    subject = _colmap_capture(tmp_path / "data")
    video_path(subject, "train", "cam01").unlink()
    _expect_capture_error(tmp_path, "cam01.mp4: camera 'cam01' in")
    with pytest.raises(StageFailed, match=r"sparse/0 has no video.*remove the camera's images from the calibration"):
        run_app(_cfg(tmp_path))


def test_a_single_uncalibrated_video_gets_the_default_field_of_view(tmp_path):
    subject = make_capture(tmp_path / "data")
    (subject / "cameras.parquet").unlink()
    for cam_id in ("cam01", "cam02"):
        video_path(subject, "train", cam_id).unlink()
    reports = run_app(_cfg(tmp_path, "dataset.default_fov_deg=90"))
    assert [r.action for r in reports] == ["run", "run"]
    capture = tmp_path / "out" / "alice" / "capture"
    (camera,) = read_cameras(capture / "cameras.parquet")
    assert camera.camera_id == "cam00" and camera.split == "train"
    np.testing.assert_allclose(camera.K, [[SIZE / 2, 0, (SIZE - 1) / 2], [0, SIZE / 2, (SIZE - 1) / 2], [0, 0, 1]])
    np.testing.assert_array_equal(camera.world_to_cam, np.eye(4))
    record = json.loads((capture / "calibration.json").read_text())
    assert record["source"] == "none: default intrinsics" and record["default_fov_deg"] == 90.0


def test_several_uncalibrated_videos_are_one_clear_error(tmp_path):
    subject = make_capture(tmp_path / "data")
    (subject / "cameras.parquet").unlink()
    _expect_capture_error(tmp_path, "only a single camera, a monocular video, may go without one")


def test_evaluate_skips_a_split_the_capture_cannot_measure(tmp_path):
    """A monocular capture has no held-out camera; one without a test sequence has no held-out motion."""
    from stages.evaluate import _unmeasurable

    make_capture(tmp_path / "data")
    capture = tmp_path / "out" / "alice" / "capture"
    run_app(_cfg(tmp_path, "run.until=capture"))
    splits = {"novel_view": ("test", "test"), "self_reenact": ("test", "train"), "seen": ("train", "train")}
    why = _unmeasurable(capture, splits)
    assert why == {
        "novel_view": "the capture has no 'test' sequence",
        "self_reenact": "the capture has no 'test' sequence",
    }
    assert _unmeasurable(capture, {"x": ("train", "held_out")}) == {
        "x": "the capture has no 'held_out' camera (a held-out view)"
    }


def _square_top(frame: np.ndarray) -> int:
    """Row where the bright square of :func:`_frames` starts (12 + source frame index)."""
    return int(np.flatnonzero((frame[..., 0] > 150).any(axis=1))[0])


def test_frame_selection_imports_every_step_th_frame_from_the_start(tmp_path):
    """start_frame / frame_step / max_frames pick source frames (videos and masks alike); fps / step."""
    subject = tmp_path / "data" / "alice"
    cams = [_camera(i) for i in range(3)]
    write_cameras(subject / "cameras.parquet", cams)
    for i, cam in enumerate(cams):
        write_video(video_path(subject, "train", cam.camera_id), _frames(i, n=7), 24.0)
        for t in range(7):
            write_png(mask_path(subject, "train", cam.camera_id, t), np.full((SIZE, SIZE), t, np.uint8))
    run_app(
        _cfg(tmp_path, "run.until=capture", "dataset.start_frame=1", "dataset.frame_step=2", "dataset.max_frames=2")
    )
    capture = tmp_path / "out" / "alice" / "capture"
    video = read_video(video_path(capture, "train", "cam01"))
    assert [_square_top(f) for f in video] == [12 + 1, 12 + 3]
    assert [int(read_png(mask_path(capture, "train", "cam01", t), 1)[0, 0]) for t in range(2)] == [1, 3]
    assert not mask_path(capture, "train", "cam01", 2).exists()
    info = CaptureIndex.read(capture).sequences["train"]
    assert info.num_frames == 2 and info.frame_rate == pytest.approx(12.0)


def test_a_video_shorter_than_the_frames_requested_is_one_clear_error(tmp_path):
    make_capture(tmp_path / "data")
    with pytest.raises(
        StageFailed,
        match=r"train/videos: 3 frames, shorter than the frames requested "
        r"\(dataset.start_frame=3\); lower dataset.start_frame",
    ):
        run_app(_cfg(tmp_path, "dataset.start_frame=3"))
    assert not (tmp_path / "out" / "alice" / "capture").exists()
    from pipeline.config import ConfigError

    for bad, message in (
        ("dataset.frame_step=0", "frame_step=0: must be >= 1"),
        ("dataset.max_frames=0", "max_frames=0: must be >= 1"),
    ):
        with pytest.raises(ConfigError, match=message):  # refused before any stage runs
            run_app(_cfg(tmp_path, bad))


def test_crop_padding_past_the_image_is_labelled_unobserved(tmp_path):
    """A subject at the image's right edge: its square crop reaches past the image, and exactly the crop
    pixels whose source lies outside the image (up to the nearest-neighbour rounding at the edge) are
    UNOBSERVED, hold the estimated background colour, and are not counted as foreground."""
    subject = make_capture(tmp_path / "data", masks=True)
    for cam in read_cameras(subject / "cameras.parquet"):
        video = np.full((FRAMES, SIZE, SIZE, 3), 90, np.uint8)
        video[:, 8:40, 30:SIZE] = (210, 160, 130)  # 32 px tall, 18 wide: the square is wider
        write_video(video_path(subject, "train", cam.camera_id), video, 25.0)
        for t in range(FRAMES):
            lab = np.zeros((SIZE, SIZE), np.uint8)
            lab[8:40, 30:SIZE] = 1
            write_png(mask_path(subject, "train", cam.camera_id, t), lab)
    run_app(_cfg(tmp_path))
    frames_dir = tmp_path / "out" / "alice" / "frames"
    index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    for seq, cam, t, (x0, _y0, size), fraction in zip(
        index["sequence"], index["camera_id"], index["frame"], index["crop"], index["foreground_fraction"]
    ):
        labels = read_png(crop_mask_path(frames_dir, seq, cam, int(t)), 1)
        rgb = read_png(rgb_path(frames_dir, seq, cam, int(t)), 3)
        out = labels.shape[0]
        source_x = x0 + (np.arange(out) + 0.5) * size / out - 0.5  # crop pixel centres in the camera image
        assert x0 + size > SIZE + 2  # the crop does reach past the image
        outside, inside = source_x > SIZE - 0.5 + 1, source_x < SIZE - 0.5 - 1
        assert (labels[:, outside] == UNOBSERVED).all() and not (labels[:, inside] == UNOBSERVED).any()
        assert (np.abs(rgb[:, outside].astype(int) - 90) <= 6).all()  # the background estimate (codec noise)
        assert fraction == pytest.approx(float((labels == 1).mean()), abs=1e-6)


def test_a_folder_capture_defaults_to_the_detectors_real_footage_needs(tmp_path):
    """Own footage needs no detector flags: dataset=folder finds the person, hand and face with MediaPipe; the
    synthetic capture's own keypoints (ground_truth) are refused on it with the settings that can run."""
    cfg = compose_cfg(["dataset=folder", "dataset.root=/data"])
    assert (cfg.stage.frames.segmenter, cfg.stage.keypoints.detector) == ("mediapipe", "mediapipe")
    assert compose_cfg([])["stage"]["keypoints"]["detector"] == "ground_truth"  # the synthetic capture's own
    make_capture(tmp_path / "data")
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path, "run.until=keypoints", "stage.keypoints.detector=ground_truth"))
    message = str(info.value)
    assert "stage.keypoints.detector=mediapipe" in message and "stage.keypoints.detector=provided" in message
    assert not (tmp_path / "out" / "alice" / "keypoints").exists()


def _as_image_folders(subject: Path, suffix: str = ".png") -> None:
    """Turn ``subject``'s train videos into ``train/images/<camera_id>/<frame>.png`` folders (then remove the
    videos), the layout many rigs and COLMAP workflows write."""
    videos = subject / "train" / "videos"
    for video in sorted(videos.glob("*.mp4")):
        folder = subject / "train" / "images" / video.stem
        folder.mkdir(parents=True)
        for t, frame in enumerate(read_video(video)):
            if suffix == ".png":
                write_png(folder / f"{t:05d}.png", frame)
            else:
                import cv2

                cv2.imwrite(str(folder / f"{t:05d}{suffix}"), frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    shutil.rmtree(videos)


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_image_folders_import_as_the_same_frames_as_videos(tmp_path, suffix):
    """Issue 36, item 3: <sequence>/images/<camera_id>/*.png (or .jpg), as conf/dataset/folder.yaml promises."""
    video_root, image_root = tmp_path / "v", tmp_path / "i"
    make_capture(video_root / "data")
    subject = make_capture(image_root / "data")
    _as_image_folders(subject, suffix)
    for root in (video_root, image_root):
        reports = run_app(_cfg(root))
        assert [r.action for r in reports] == ["run", "run"]
    a = read_table(video_root / "out" / "alice" / "frames" / "index.parquet", FRAMES_INDEX)
    b = read_table(image_root / "out" / "alice" / "frames" / "index.parquet", FRAMES_INDEX)
    assert len(b["frame"]) == len(a["frame"]) == 3 * FRAMES
    index = CaptureIndex.read(image_root / "out" / "alice" / "capture")
    assert index.sequences["train"].num_frames == FRAMES
    for cam in ("cam00", "cam01", "cam02"):  # the imported videos hold the same pictures (codec and JPEG aside)
        original = read_video(video_path(video_root / "out" / "alice" / "capture", "train", cam)).astype(float)
        imported = read_video(video_path(image_root / "out" / "alice" / "capture", "train", cam)).astype(float)
        assert imported.shape == original.shape
        assert np.abs(imported - original).mean() < 3.0


def test_image_folder_errors_name_the_folder(tmp_path):
    subject = make_capture(tmp_path / "data")
    _as_image_folders(subject)
    empty = subject / "train" / "images" / "cam01"
    for image in empty.iterdir():
        image.unlink()
    _expect_capture_error(tmp_path, f"{empty}: image folder without")
    shutil.rmtree(subject)
    subject = make_capture(tmp_path / "data")
    _as_image_folders(subject)
    odd = subject / "train" / "images" / "cam02" / "00001.png"
    write_png(odd, np.zeros((SIZE + 2, SIZE, 3), np.uint8))
    _expect_capture_error(tmp_path, f"{odd}: image is {SIZE}x{SIZE + 2}")
    shutil.rmtree(subject)
    subject = make_capture(tmp_path / "data")
    _as_image_folders(subject)
    make_capture(tmp_path / "data")  # the videos again, beside the images
    _expect_capture_error(tmp_path, "has both videos/ and images/")
