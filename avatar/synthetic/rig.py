"""The synthetic studio's camera rig: calibrated pinhole cameras on the frontal
hemisphere, all aimed at the head/hand region.

World frame: metres, y up, the subject faces +z. Cameras use OpenCV axes
(x right, y down, z forward) and OpenCV's pixel convention (pixel (i, j) has its
centre at (x, y) = (j, i), so a centred principal point is (W/2 - 0.5, H/2 - 0.5)),
like every artifact of the project. :func:`mesh_raster_camera` converts to the
mesh rasterizer's convention (pixel centres at +0.5).

Layout: azimuths spread evenly over [-65, 65] degrees (0 = straight in front),
elevations and distances (0.6-0.9 m) vary per camera; the camera at index
``n // 2 - 1`` -- between its two azimuthal neighbours, never an extreme view --
is the held-out 'test' view, the others are 'train'. The rig is fixed: it
depends on the number of cameras and the image size only.
"""

from __future__ import annotations

import numpy as np

from avatar.render.mesh_raster import PinholeCamera
from data_schemas.cameras import Camera

AZIMUTH_RANGE_DEG = 65.0
ELEVATIONS_DEG = (8.0, -6.0, 20.0, 2.0, 14.0, -4.0, 24.0, 6.0)
DISTANCES_M = (0.80, 0.66, 0.75, 0.62, 0.70, 0.85, 0.78, 0.90)
#: Half-width of the world region (metres, at the aim point) that fills the image.
FIELD_HALF_WIDTH_M = 0.18


def mesh_raster_camera(camera: Camera) -> PinholeCamera:
    """The camera for :mod:`avatar.render.mesh_raster`, whose pixel centres sit at +0.5."""
    K = camera.K.copy()
    K[:2, 2] += 0.5
    return PinholeCamera(K=K, world_to_cam=camera.world_to_cam, width=camera.width, height=camera.height)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera transform of a camera at ``eye`` looking at
    ``target`` with world ``up`` appearing upwards (OpenCV axes)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)  # x axis: right in the image
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)  # y axis: down in the image
    rot = np.stack([right, down, forward])  # rows: camera axes in world
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    return m


def held_out_index(num_cameras: int) -> int:
    """The index of the rig's held-out 'test' camera: ``n // 2 - 1``, between its two azimuthal neighbours."""
    return num_cameras // 2 - 1


def make_rig(num_cameras: int, image_size: int, target: np.ndarray) -> list[Camera]:
    """Cameras around ``target`` (3,) world metres, square ``image_size`` images.

    The focal length makes a window of +-FIELD_HALF_WIDTH_M around the target
    fill the image at every camera's distance.
    """
    if num_cameras < 2:
        raise ValueError(f"the rig needs >= 2 cameras (train + test), got {num_cameras}")
    azimuths = np.linspace(-AZIMUTH_RANGE_DEG, AZIMUTH_RANGE_DEG, num_cameras)
    test_index = held_out_index(num_cameras)
    up = np.array([0.0, 1.0, 0.0])
    cams = []
    for i, az in enumerate(azimuths):
        el = np.deg2rad(ELEVATIONS_DEG[i % len(ELEVATIONS_DEG)])
        dist = DISTANCES_M[i % len(DISTANCES_M)]
        a = np.deg2rad(az)
        direction = np.array([np.sin(a) * np.cos(el), np.sin(el), np.cos(a) * np.cos(el)])
        eye = target + dist * direction
        focal = image_size / 2 * dist / FIELD_HALF_WIDTH_M
        centre = image_size / 2 - 0.5
        k = np.array([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]])
        cams.append(
            Camera(
                camera_id=f"cam{i:02d}",
                width=image_size,
                height=image_size,
                K=k,
                world_to_cam=look_at(eye, target, up),
                dist=np.zeros(5),
                split="test" if i == test_index else "train",
            )
        )
    return cams
