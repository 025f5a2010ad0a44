"""Registered images of a calibration, grouped into the rig's cameras.

A calibration tool registers *images*; a capture has *cameras*, one video each. An image belongs to the
camera named by its folder (``cam04/000000.png``) or, when it has none, by its file stem (``cam04.jpg``).
Every image of one camera must agree on the intrinsics and the pose (a static rig).

Pixel convention: COLMAP and nerfstudio put the centre of the top-left pixel at (0.5, 0.5), OpenCV (and
this project) at (0, 0), so the principal point moves by -0.5 px on import (:data:`PIXEL_CENTRE_SHIFT`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePosixPath

import numpy as np

from data_schemas.cameras import SPLITS, Camera
from data_schemas.tables import SchemaError

PIXEL_CENTRE_SHIFT = -0.5  # COLMAP / nerfstudio principal point -> OpenCV's
POSE_TOLERANCE = 1e-6  # images of one camera: largest difference of their world-to-camera entries (units)


@dataclass(frozen=True)
class CalibratedImage:
    """One registered image: ``K`` (3, 3) px in OpenCV's pixel convention, ``dist`` (D,) OpenCV
    coefficients (k1 k2 p1 p2 [k3 k4 k5 k6]), ``world_to_cam`` (4, 4) OpenCV axes, calibration units."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    world_to_cam: np.ndarray


def camera_id_of(image_name: str) -> str:
    """The camera an image belongs to: its first folder, else its file stem."""
    path = PurePosixPath(image_name.replace("\\", "/"))
    return path.parts[0] if len(path.parts) > 1 else path.stem


def pinhole(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) OpenCV intrinsics from a COLMAP / nerfstudio focal length and principal point."""
    return np.array([[fx, 0.0, cx + PIXEL_CENTRE_SHIFT], [0.0, fy, cy + PIXEL_CENTRE_SHIFT], [0.0, 0.0, 1.0]])


def rig_cameras(
    images: Sequence[CalibratedImage], source: str, scale_m: float, test_cameras: Sequence[str] | None
) -> list[Camera]:
    """One :class:`Camera` per camera of the rig, translations scaled to metres by ``scale_m`` (metres per
    calibration unit); ``test_cameras`` held out for novel views (None: the last id in sorted order).
    Raises :class:`SchemaError` naming ``source`` for non-finite values, disagreeing images of one camera,
    or a held-out list that names no camera or every camera."""
    if not np.isfinite(scale_m) or scale_m <= 0:
        raise SchemaError(
            f"{source}: the scale must be a positive number of metres per calibration unit, "
            f"got {scale_m}; set dataset.calibration_scale_m"
        )
    by_camera: dict[str, CalibratedImage] = {}
    for image in images:
        for what, value in (("intrinsics", image.K), ("distortion", image.dist), ("pose", image.world_to_cam)):
            if not np.isfinite(value).all():
                raise SchemaError(f"{source}: image '{image.name}' has non-finite {what}; fix or remove it")
        cam_id = camera_id_of(image.name)
        first = by_camera.setdefault(cam_id, image)
        if not _same_view(first, image):
            raise SchemaError(
                f"{source}: images '{first.name}' and '{image.name}' belong to camera '{cam_id}' but "
                f"differ in size, intrinsics or pose; a capture needs a static rig (one calibration "
                f"per camera): keep one image per camera, or name the images <camera>/<frame>"
            )
    if not by_camera:
        raise SchemaError(f"{source}: no registered image; calibrate at least two cameras")
    ids = sorted(by_camera)
    held_out = [str(c) for c in test_cameras] if test_cameras is not None else ids[-1:]
    unknown = sorted(set(held_out) - set(ids))
    if unknown or not held_out or len(set(held_out)) >= len(ids):
        raise SchemaError(f"{source}: dataset.test_cameras={held_out}: choose some but not all of the cameras {ids}")
    dist_len = max(len(by_camera[c].dist) for c in ids)
    cameras = []
    for cam_id in ids:
        image = by_camera[cam_id]
        w2c = image.world_to_cam.astype(np.float64).copy()
        w2c[:3, 3] *= scale_m
        dist = np.zeros(dist_len)
        dist[: len(image.dist)] = image.dist  # OpenCV reads missing trailing coefficients as zero
        cameras.append(
            Camera(
                camera_id=cam_id,
                width=image.width,
                height=image.height,
                K=image.K.astype(np.float64),
                world_to_cam=w2c,
                dist=dist,
                split=SPLITS[1] if cam_id in held_out else SPLITS[0],
            )
        )
    return cameras


def _same_view(a: CalibratedImage, b: CalibratedImage) -> bool:
    return (
        (a.width, a.height) == (b.width, b.height)
        and np.allclose(a.K, b.K, rtol=0, atol=1e-6)
        and len(a.dist) == len(b.dist)
        and np.allclose(a.dist, b.dist, rtol=0, atol=1e-9)
        and np.allclose(a.world_to_cam, b.world_to_cam, rtol=0, atol=POSE_TOLERANCE)
    )
