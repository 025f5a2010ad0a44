"""Stage ``frames``: decode every view, masks and part boxes, square crops with adjusted intrinsics."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatar.preprocess.crops import SquareCrop, label_box, square_crop, union_box
from avatar.preprocess.masks import background_colour, key_foreground
from avatar.preprocess.mediapipe_detect import HANDEDNESS, LandmarkDetector, SelfieSegmenter, part_labels
from data_schemas.cameras import Camera, read_cameras
from data_schemas.capture import MASK_LABELS, CaptureIndex, mask_path, video_path
from data_schemas.frames import FRAMES_INDEX, UNKNOWN_PART, UNOBSERVED, crop_mask_path, rgb_path
from data_schemas.images import read_png, write_png
from data_schemas.tables import SchemaError, write_table
from data_schemas.video import read_video
from pipeline.stage import StageContext, stage

SEGMENTERS = ("key", "mediapipe")


@dataclass
class MediapipeSegmenterConfig:
    """``stage.frames.mediapipe``: settings of segmenter=mediapipe."""

    threshold: float
    parts: bool
    handedness: str
    mirrored: bool


@dataclass
class FramesConfig:
    """Types of ``stage.frames`` (values in conf/stage/frames.yaml)."""

    margin: float
    key_threshold: float
    segmenter: str
    mediapipe: MediapipeSegmenterConfig


@stage(
    "frames",
    inputs=("capture",),
    config_keys=("quality.image_size", "stage.frames"),
    outputs=("index.parquet",),
    version="2",  # 2: crop padding is labelled UNOBSERVED (was background)
    config_schema=FramesConfig,
)
def frames(ctx: StageContext) -> None:
    """Decode views, take masks, track part boxes and write square crops of quality.image_size."""
    cap_dir = ctx.input_dir("capture")
    index = CaptureIndex.read(cap_dir)
    cameras = read_cameras(cap_dir / "cameras.parquet")
    conf, size = ctx.cfg.stage.frames, int(ctx.cfg.quality.image_size)
    if conf.segmenter not in SEGMENTERS:
        raise SchemaError(f"stage.frames.segmenter={conf.segmenter!r}: choose one of {SEGMENTERS}")
    if conf.mediapipe.handedness not in HANDEDNESS:
        raise SchemaError(
            f"stage.frames.mediapipe.handedness={conf.mediapipe.handedness!r}: choose one of {HANDEDNESS}"
        )
    rows: dict[str, list] = {c.name: [] for c in FRAMES_INDEX.columns}
    jobs = [(seq, cam) for seq in index.sequences for cam in cameras]
    for seq, cam in ctx.progress(jobs, desc="frames: views"):
        info = index.sequences[seq]
        video = read_video(video_path(cap_dir, seq, cam.camera_id))
        if video.shape[:3] != (info.num_frames, cam.height, cam.width):
            raise SchemaError(
                f"{video_path(cap_dir, seq, cam.camera_id)}: {video.shape[:3]} (frames, H, W) but the "
                f"capture says {(info.num_frames, cam.height, cam.width)}; rerun capture"
            )
        labels = _labels(cap_dir, seq, cam, video, info.has_masks, conf)
        crop = _sequence_crop(labels, conf.margin, size)
        _write_view(ctx.out_dir, seq, cam, video, labels, crop, rows)
    write_table(
        ctx.out_dir / "index.parquet",
        FRAMES_INDEX,
        {k: (v if FRAMES_INDEX.column(k).kind == "string" else np.asarray(v)) for k, v in rows.items()},
    )
    ctx.metrics["views"] = len(cameras)
    ctx.metrics["crops"] = len(rows["frame"])
    ctx.metrics["hand_visible_fraction"] = float(np.mean(rows["hand_visible"]))
    ctx.metrics["foreground_fraction"] = float(np.mean(rows["foreground_fraction"]))


def _labels(cap_dir: Path, seq: str, cam: Camera, video: np.ndarray, has_masks: bool, conf: FramesConfig) -> np.ndarray:
    """(T, H, W) uint8 part labels: the capture's masks, else the configured segmenter's."""
    if has_masks:
        labels = np.stack([read_png(mask_path(cap_dir, seq, cam.camera_id, t), 1) for t in range(len(video))])
        fix = "fix or delete the mask (without masks the stage segments with stage.frames.segmenter)"
    elif conf.segmenter == "mediapipe":
        labels = _segment_mediapipe(video, conf.mediapipe)
        fix = (
            "MediaPipe's selfie segmentation found no person; check the video or lower stage.frames.mediapipe.threshold"
        )
    else:
        labels = key_foreground(video, background_colour(video), conf.key_threshold) * UNKNOWN_PART
        fix = "the subject must be visible in every view and frame; check the video or lower stage.frames.key_threshold"
    empty = np.flatnonzero(labels.reshape(len(labels), -1).max(axis=1) == 0)
    if len(empty):
        t = int(empty[0])
        source = mask_path(cap_dir, seq, cam.camera_id, t) if has_masks else video_path(cap_dir, seq, cam.camera_id)
        raise SchemaError(f"{source}: empty foreground mask in frame {t} of camera '{cam.camera_id}'; {fix}")
    return labels


def _segment_mediapipe(video: np.ndarray, conf: MediapipeSegmenterConfig) -> np.ndarray:
    """(T, H, W) uint8 labels: selfie segmentation for the foreground; with ``conf.parts`` face and
    hand from the landmark hulls, the rest of the person UNKNOWN_PART."""
    feature = "stage.frames.segmenter=mediapipe"
    with SelfieSegmenter(feature=feature) as segment:
        foreground = np.stack([segment(frame) > conf.threshold for frame in video])
    if not conf.parts:
        return foreground.astype(np.uint8) * UNKNOWN_PART
    with LandmarkDetector(handedness=conf.handedness, mirrored=conf.mirrored, feature=feature) as detector:
        return np.stack(
            [
                part_labels(fg, detector.detect(frame), MASK_LABELS["face"], MASK_LABELS["hand"], UNKNOWN_PART)
                for frame, fg in zip(video, foreground)
            ]
        )


def _sequence_crop(labels: np.ndarray, margin: float, size: int) -> SquareCrop:
    """One square crop per view and sequence, around all foreground in all frames."""
    boxes = [label_box((frame > 0).astype(np.uint8), 1) for frame in labels]
    return square_crop(union_box([b for b in boxes if b is not None]), margin, size)


def _write_view(
    out: Path, seq: str, cam: Camera, video: np.ndarray, labels: np.ndarray, crop: SquareCrop, rows: dict[str, list]
) -> None:
    """Write the crops of one view: RGB padded with the background colour where the crop reaches past the
    image, labels padded with UNOBSERVED there (so no loss or metric compares a render with the padding)."""
    fill = background_colour(video).astype(np.uint8)
    K = crop.adjust_intrinsics(cam.K)
    for t in range(len(video)):
        rgb = crop.apply(video[t], fill)
        lab = crop.apply(labels[t], UNOBSERVED, labels=True)
        write_png(rgb_path(out, seq, cam.camera_id, t), rgb)
        write_png(crop_mask_path(out, seq, cam.camera_id, t), lab)
        face = label_box(lab, MASK_LABELS["face"])
        hand = label_box(lab, MASK_LABELS["hand"])
        rows["sequence"].append(seq)
        rows["camera_id"].append(cam.camera_id)
        rows["frame"].append(t)
        rows["split"].append(cam.split)
        rows["crop"].append([crop.x0, crop.y0, crop.size])
        rows["K"].append(K.reshape(9))
        rows["face_box"].append(face if face is not None else np.zeros(4))
        rows["hand_box"].append(hand if hand is not None else np.zeros(4))
        rows["face_visible"].append(face is not None)
        rows["hand_visible"].append(hand is not None)
        rows["foreground_fraction"].append(float(((lab > 0) & (lab != UNOBSERVED)).mean()))
