"""Cameras for watching a reenactment: a capture camera cropped to the performance, and an orbit.

OpenCV conventions: ``world_to_cam`` (4, 4) maps world points to camera axes x right, y down, z forward;
``K`` (3, 3) in pixels with pixel centres at integer coordinates.
"""

from __future__ import annotations

import cv2
import numpy as np

from avatar.preprocess.crops import square_crop


def framed_intrinsics(
    K: np.ndarray, world_to_cam: np.ndarray, points: np.ndarray, size: int, margin: float = 0.1
) -> np.ndarray:
    """(3, 3) intrinsics of a ``size`` px square crop of camera (``K``, ``world_to_cam``) holding every one of
    ``points`` (N, 3) (e.g. the face and hand vertices of all frames), grown by ``margin``."""
    cam = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    if (cam[:, 2] <= 1e-6).any():
        raise ValueError("some points are behind the camera; choose another camera")
    uv = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    box = np.concatenate([uv.min(0), uv.max(0)])
    return square_crop(box, margin, size).adjust_intrinsics(K)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera of a camera at ``eye`` looking at ``target`` with ``up`` (world) pointing up in
    the image."""
    z = target - eye
    z = z / np.linalg.norm(z)
    y = -up - np.dot(-up, z) * z
    norm = np.linalg.norm(y)
    if norm < 1e-9:
        raise ValueError("the up direction is parallel to the viewing direction")
    y = y / norm
    x = np.cross(y, z)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, z])
    out[:3, 3] = -out[:3, :3] @ eye
    return out


def orbit(eye: np.ndarray, target: np.ndarray, up: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` world-to-camera matrices on one turn around the axis through ``target`` along ``up``,
    starting at ``eye`` and always looking at ``target``."""
    axis = up / np.linalg.norm(up)
    offset = eye - target
    cameras = []
    for angle in np.linspace(0.0, 2 * np.pi, count, endpoint=False):
        c, s = np.cos(angle), np.sin(angle)
        rotated = offset * c + np.cross(axis, offset) * s + axis * np.dot(axis, offset) * (1 - c)  # Rodrigues
        cameras.append(look_at(target + rotated, target, axis))
    return cameras


def orbit_intrinsics(distance: float, radius: float, size: int) -> np.ndarray:
    """(3, 3) intrinsics of a ``size`` px camera at ``distance`` from a sphere of ``radius`` that it frames."""
    focal = 0.5 * size * distance / radius
    centre = (size - 1) / 2
    return np.array([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]])


def reframe(
    image: np.ndarray,
    K_from: np.ndarray,
    K_to: np.ndarray,
    size: int,
    background: tuple[float, float, float] = (255.0, 255.0, 255.0),
) -> np.ndarray:
    """A ``size`` px square view (size, size, C) of ``image`` (H, W, C) as the same camera with intrinsics
    ``K_to`` instead of ``K_from`` (both (3, 3), no skew) would see it: pixel x' = K_to K_from^-1 x, an affine
    map, resampled bilinearly; pixels outside the source get ``background``. Used to put a capture's ground
    truth beside a render made with :func:`framed_intrinsics`."""
    affine = (K_to @ np.linalg.inv(K_from))[:2]
    return cv2.warpAffine(
        image, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=background
    )
