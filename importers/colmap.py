"""COLMAP sparse models (``cameras.bin``/``images.bin`` or the ``.txt`` versions), read with pycolmap.

Camera models OpenCV's pinhole-plus-distortion model expresses (:data:`OPENCV_MODELS`) are converted;
any other (fisheye and the rest) is one clear error that says how to get a pinhole model.
COLMAP's ``cam_from_world`` already uses OpenCV's axes (x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from data_schemas.tables import SchemaError
from importers.calibrated_images import CalibratedImage, pinhole

Intrinsics = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

# COLMAP model -> (params) -> (K (3, 3), OpenCV dist (D,)); parameter orders from COLMAP's models.h.
OPENCV_MODELS: dict[str, Intrinsics] = {
    "SIMPLE_PINHOLE": lambda p: (pinhole(p[0], p[0], p[1], p[2]), np.zeros(4)),
    "PINHOLE": lambda p: (pinhole(p[0], p[1], p[2], p[3]), np.zeros(4)),
    "SIMPLE_RADIAL": lambda p: (pinhole(p[0], p[0], p[1], p[2]), np.array([p[3], 0.0, 0.0, 0.0])),
    "RADIAL": lambda p: (pinhole(p[0], p[0], p[1], p[2]), np.array([p[3], p[4], 0.0, 0.0])),
    "OPENCV": lambda p: (pinhole(p[0], p[1], p[2], p[3]), np.asarray(p[4:8], dtype=np.float64)),
    # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's rational model, the same order
    "FULL_OPENCV": lambda p: (pinhole(p[0], p[1], p[2], p[3]), np.asarray(p[4:12], dtype=np.float64)),
}
MODEL_FILES = ("cameras.bin", "cameras.txt")


def find_model(folder: Path) -> Path | None:
    """The COLMAP model folder in ``folder``: itself, ``sparse/0`` or ``sparse`` (COLMAP's own layout)."""
    for candidate in (folder, folder / "sparse" / "0", folder / "sparse"):
        if any((candidate / name).is_file() for name in MODEL_FILES):
            return candidate
    return None


def read_colmap(model_dir: Path) -> list[CalibratedImage]:
    """Every registered image of the model in ``model_dir``, in COLMAP's units (scale arbitrary)."""
    import pycolmap  # imported here: only COLMAP calibrations need it

    try:
        reconstruction = pycolmap.Reconstruction(str(model_dir))
    except (RuntimeError, ValueError) as exc:
        raise SchemaError(
            f"{model_dir}: not a readable COLMAP model ({exc}); it needs cameras, images (and "
            f"points3D) as .bin or .txt, as colmap mapper or model_converter write them"
        ) from exc
    images = []
    for image in sorted(reconstruction.images.values(), key=lambda i: i.name):
        if not image.has_pose:
            continue  # not registered: COLMAP keeps it in the model without a pose
        camera = reconstruction.cameras[image.camera_id]
        model = camera.model.name
        if model not in OPENCV_MODELS:
            raise SchemaError(
                f"{model_dir}: camera {image.camera_id} (image '{image.name}') uses COLMAP's {model} "
                f"model, which OpenCV's pinhole-and-distortion model cannot express (supported: "
                f"{', '.join(OPENCV_MODELS)}); run `colmap image_undistorter` and import its "
                f"PINHOLE model and undistorted images instead"
            )
        K, dist = OPENCV_MODELS[model](np.asarray(camera.params, dtype=np.float64))
        world_to_cam = np.eye(4)
        world_to_cam[:3] = image.cam_from_world().matrix()
        images.append(
            CalibratedImage(
                name=image.name,
                width=int(camera.width),
                height=int(camera.height),
                K=K,
                dist=dist,
                world_to_cam=world_to_cam,
            )
        )
    return images
