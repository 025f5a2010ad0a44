"""Stage ``keypoints``: 2D hand and face keypoints per frame and camera."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatar.fitting.noise import corrupt_keypoints
from avatar.preprocess.mediapipe_detect import HANDEDNESS, LandmarkDetector
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, gt_path, provided_path, video_path
from data_schemas.keypoints import KEYPOINTS, PARTS
from data_schemas.tables import SchemaError, read_table, write_table
from data_schemas.video import read_video
from pipeline.stage import StageContext, stage

DETECTORS = ("ground_truth", "mediapipe", "provided")


@dataclass
class MediapipeConfig:
    """``stage.keypoints.mediapipe``: settings of detector=mediapipe (see avatar/preprocess/mediapipe_detect.py)."""

    tracking: bool
    min_confidence: float
    handedness: str
    mirrored: bool


@dataclass
class KeypointsConfig:
    """Types of ``stage.keypoints`` (values in conf/stage/keypoints.yaml)."""

    detector: str
    pixel_noise: float
    drop_rate: float
    outlier_rate: float
    seed: int
    mediapipe: MediapipeConfig


@stage(
    "keypoints",
    inputs=("capture",),
    config_keys=("stage.keypoints",),
    outputs=("train/keypoints.parquet",),
    version="2",
    config_schema=KeypointsConfig,
)
def keypoints(ctx: StageContext) -> None:
    """Detect (or, for the synthetic capture, corrupt the projected ground-truth) 2D keypoints."""
    conf = ctx.cfg.stage.keypoints
    if conf.detector not in DETECTORS:
        raise SchemaError(f"stage.keypoints.detector={conf.detector!r}: available detectors are {DETECTORS}")
    cap_dir = ctx.input_dir("capture")
    index = CaptureIndex.read(cap_dir)
    if conf.detector == "mediapipe":
        _detect_mediapipe(ctx, cap_dir, index, conf.mediapipe)
        return
    if conf.detector == "provided":
        _copy_provided(ctx, cap_dir, index)
        return
    sizes = {c.camera_id: (c.width, c.height) for c in read_cameras(cap_dir / "cameras.parquet")}
    rng = np.random.default_rng(conf.seed)
    detected = 0
    for seq, info in index.sequences.items():
        if not info.has_ground_truth:
            raise SchemaError(
                f"{cap_dir / seq}: stage.keypoints.detector=ground_truth needs a capture with "
                f"ground-truth keypoints (dataset=synthetic), and this '{index.dataset}' capture has "
                f"none: set stage.keypoints.detector=mediapipe to detect them (real footage; "
                f"docs/how-to/real-footage.md) or stage.keypoints.detector=provided for keypoints "
                f"shipped with the dataset"
            )
        table = read_table(gt_path(cap_dir, seq, "keypoints"), KEYPOINTS)
        uvc = [
            corrupt_keypoints(
                np.asarray(kp, np.float64).reshape(-1, 3),
                conf.pixel_noise,
                conf.drop_rate,
                conf.outlier_rate,
                sizes[cam],
                rng,
            )
            for kp, cam in zip(table["uvc"], table["camera_id"])
        ]
        detected += int(sum((k[:, 2] > 0).sum() for k in uvc))
        write_table(ctx.out_dir / seq / "keypoints.parquet", KEYPOINTS, {**table, "uvc": uvc})
    ctx.metrics["detections"] = detected


def _detect_mediapipe(ctx: StageContext, cap_dir: Path, index: CaptureIndex, conf: MediapipeConfig) -> None:
    """MediaPipe face (68) and right-hand (21) landmarks on every frame of every view, in full-image
    pixels; a part not found in a frame gets confidence 0. pixel_noise, drop_rate and outlier_rate
    do not apply (they corrupt synthetic ground truth)."""
    if conf.handedness not in HANDEDNESS:
        raise SchemaError(f"stage.keypoints.mediapipe.handedness={conf.handedness!r}: choose one of {HANDEDNESS}")
    cameras = read_cameras(cap_dir / "cameras.parquet")
    found = dict.fromkeys(PARTS, 0)
    frames_seen = detected = 0
    for seq in index.sequences:
        rows: dict[str, list] = {"frame": [], "camera_id": [], "part": [], "uvc": []}
        for cam in ctx.progress(cameras, desc=f"keypoints: {seq} views"):
            video = read_video(video_path(cap_dir, seq, cam.camera_id))
            with LandmarkDetector(
                conf.tracking,
                conf.min_confidence,
                conf.handedness,
                conf.mirrored,
                feature="stage.keypoints.detector=mediapipe",
            ) as detector:
                detections = [detector.detect(frame) for frame in video]
            frames_seen += len(video)
            for part in PARTS:
                for t, det in enumerate(detections):
                    uvc = getattr(det, part)
                    found[part] += bool(uvc[:, 2].any())
                    detected += int((uvc[:, 2] > 0).sum())
                    rows["frame"].append(t)
                    rows["camera_id"].append(cam.camera_id)
                    rows["part"].append(part)
                    rows["uvc"].append(uvc.astype(np.float32).reshape(-1))
        write_table(ctx.out_dir / seq / "keypoints.parquet", KEYPOINTS, {**rows, "frame": np.array(rows["frame"])})
    ctx.metrics["detections"] = detected
    for part in PARTS:
        ctx.metrics[f"{part}_found_fraction"] = found[part] / max(frames_seen, 1)


def _copy_provided(ctx: StageContext, cap_dir: Path, index: CaptureIndex) -> None:
    """The keypoints the dataset ships (DECAF: face_alignment landmarks and MediaPipe hand keypoints),
    as they are: pixel_noise, drop_rate and outlier_rate do not apply."""
    detected = 0
    for seq, info in index.sequences.items():
        if not info.has_provided("keypoints"):
            raise SchemaError(
                f"{cap_dir / seq}: detector=provided needs keypoints shipped with the dataset "
                f"(dataset=decaf), but the '{index.dataset}' capture of '{index.subject}' has none "
                f"for sequence '{seq}'{''.join('; ' + n for n in info.notes if 'keypoints' in n)}"
            )
        table = read_table(provided_path(cap_dir, seq, "keypoints"), KEYPOINTS)
        detected += int(sum((np.reshape(k, (-1, 3))[:, 2] > 0).sum() for k in table["uvc"]))
        write_table(ctx.out_dir / seq / "keypoints.parquet", KEYPOINTS, table)
    ctx.metrics["detections"] = detected
