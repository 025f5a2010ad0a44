"""nerfstudio ``transforms.json``: intrinsics shared at the top level or per frame, camera-to-world in
OpenGL's axes (x right, y up, z backward), converted to OpenCV's (x right, y down, z forward).

Fisheye and equirectangular models are refused with one clear error. ``OPENCV`` (the default) reads
k1 k2 p1 p2 and k3 into OpenCV's order (k1 k2 p1 p2 k3); a non-zero k4 (nerfstudio's r^8 term, which
OpenCV's standard model lacks) is refused too.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from data_schemas.tables import SchemaError
from importers.calibrated_images import CalibratedImage, camera_id_of, pinhole

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: flip y and z (right-multiplied on cam_to_world)
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def read_transforms(path: Path) -> list[CalibratedImage]:
    """Every frame of ``transforms.json`` as a registered image, in its units (scale arbitrary)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SchemaError(f"{path}: not a readable transforms.json ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise SchemaError(f"{path}: needs a non-empty 'frames' list of {{file_path, transform_matrix}}")
    images: list[CalibratedImage] = []
    sizes: dict[str, tuple[int, int]] = {}
    for i, frame in enumerate(data["frames"]):
        where = f"{path}: frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise SchemaError(f"{where}: needs 'file_path' and 'transform_matrix' (4x4 camera-to-world)")
        fields = {**data, **frame}  # per-frame intrinsics override the shared ones
        model = str(fields.get("camera_model", "OPENCV"))
        if model not in PINHOLE_MODELS:
            raise SchemaError(
                f"{where}: camera_model {model} is not a pinhole model OpenCV's standard distortion "
                f"expresses (use one of {PINHOLE_MODELS}); undistort the images first"
            )
        missing = [k for k in INTRINSIC_KEYS if k not in fields and not (k == "fl_y" and "fl_x" in fields)]
        if missing:
            raise SchemaError(f"{where}: intrinsics {missing} missing (neither shared nor per frame)")
        name = _image_name(str(frame["file_path"]))
        size = (int(fields["w"]), int(fields["h"]))
        camera = camera_id_of(name)
        if sizes.setdefault(camera, size) != size:
            raise SchemaError(
                f"{where}: image '{name}' is {size[0]}x{size[1]} but an earlier image of camera "
                f"'{camera}' is {sizes[camera][0]}x{sizes[camera][1]}; the sizes must agree"
            )
        K = pinhole(
            float(fields["fl_x"]), float(fields.get("fl_y", fields["fl_x"])), float(fields["cx"]), float(fields["cy"])
        )
        if float(fields.get("k4", 0.0)) != 0.0:
            raise SchemaError(
                f"{where}: k4 (an r^8 radial term) is not in OpenCV's standard distortion model; "
                f"undistort the images first"
            )
        dist = np.array([float(fields.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])
        cam_to_world = _matrix(where, frame["transform_matrix"]) @ OPENGL_TO_OPENCV
        images.append(
            CalibratedImage(
                name=name, width=size[0], height=size[1], K=K, dist=dist, world_to_cam=np.linalg.inv(cam_to_world)
            )
        )
    return images


def _image_name(file_path: str) -> str:
    """``images/cam04/0001.png`` or ``./images/cam04.png`` -> the name below nerfstudio's ``images`` folder."""
    parts = [p for p in file_path.replace("\\", "/").split("/") if p not in ("", ".")]
    if parts and parts[0].startswith("images"):
        parts = parts[1:]
    return "/".join(parts)


def _matrix(where: str, value: Any) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{where}: transform_matrix is not numeric ({exc})") from exc
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise SchemaError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) camera-to-world matrix")
    R = m[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise SchemaError(f"{where}: transform_matrix is not a rigid transform (scaled or mirrored rotation)")
    return m
