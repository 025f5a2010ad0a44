"""Stage ``keypoints``: 2D hand and face keypoints per frame and camera."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatar.fitting.noise import corrupt_keypoints
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, gt_path
from data_schemas.keypoints import KEYPOINTS
from data_schemas.tables import SchemaError, read_table, write_table
from pipeline.stage import StageContext, stage

DETECTORS = ("ground_truth",)


@dataclass
class KeypointsConfig:
    """Types of ``stage.keypoints`` (values in conf/stage/keypoints.yaml)."""

    detector: str
    pixel_noise: float
    drop_rate: float
    outlier_rate: float
    seed: int


@stage("keypoints", inputs=("capture",), config_keys=("stage.keypoints",), outputs=("train/keypoints.parquet",),
       version="1", config_schema=KeypointsConfig)
def keypoints(ctx: StageContext) -> None:
    """Detect (or, for the synthetic capture, corrupt the projected ground-truth) 2D keypoints."""
    conf = ctx.cfg.stage.keypoints
    if conf.detector not in DETECTORS:
        raise SchemaError(f"stage.keypoints.detector={conf.detector!r}: available detectors are {DETECTORS}")
    cap_dir = ctx.input_dir("capture")
    index = CaptureIndex.read(cap_dir)
    sizes = {c.camera_id: (c.width, c.height) for c in read_cameras(cap_dir / "cameras.parquet")}
    rng = np.random.default_rng(conf.seed)
    detected = 0
    for seq, info in index.sequences.items():
        if not info.has_ground_truth:
            raise SchemaError(f"{cap_dir / seq}: detector=ground_truth needs a capture with ground-truth keypoints "
                              f"(dataset=synthetic)")
        table = read_table(gt_path(cap_dir, seq, "keypoints"), KEYPOINTS)
        uvc = [corrupt_keypoints(np.asarray(kp, np.float64).reshape(-1, 3), conf.pixel_noise, conf.drop_rate,
                                 conf.outlier_rate, sizes[cam], rng)
               for kp, cam in zip(table["uvc"], table["camera_id"])]
        detected += int(sum((k[:, 2] > 0).sum() for k in uvc))
        write_table(ctx.out_dir / seq / "keypoints.parquet", KEYPOINTS, {**table, "uvc": uvc})
    ctx.metrics["detections"] = detected
