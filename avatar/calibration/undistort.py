"""Undistort images once at import, so that every later stage sees a pinhole camera with the same ``K``.

The new image keeps the camera's ``K`` (OpenCV's ``initUndistortRectifyMap`` with ``newCameraMatrix=K``):
a pixel (u, v) of the result is the pinhole projection of the ray that the distorted camera saw at
``distort(u, v)``. Colours are interpolated bilinearly with edge pixels repeated; part masks take the
nearest label, with 0 (background) where the source lies outside the image.
"""

from __future__ import annotations

import cv2
import numpy as np


def is_distorted(dist: np.ndarray) -> bool:
    """Whether OpenCV distortion coefficients ``dist`` (D,) move any pixel."""
    return bool(np.any(np.asarray(dist) != 0.0))


class Undistorter:
    """The remap of one camera: ``K`` (3, 3), ``dist`` (D,), image ``width`` x ``height``."""

    def __init__(self, K: np.ndarray, dist: np.ndarray, width: int, height: int) -> None:
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(
            np.asarray(K, np.float64),
            np.asarray(dist, np.float64),
            None,
            np.asarray(K, np.float64),
            (int(width), int(height)),
            cv2.CV_32FC1,
        )

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> the same camera without distortion."""
        return cv2.remap(rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def labels(self, mask: np.ndarray) -> np.ndarray:
        """(H, W) uint8 part labels -> the same camera without distortion (nearest label)."""
        return cv2.remap(mask, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
