"""Ground-truth 2D keypoints: projection plus an in-image and depth-buffer
visibility test.

A keypoint is visible when it projects inside the image and nothing in the
depth buffer is nearer than its own depth by more than a tolerance. Hand
keypoints include joint centres, which lie inside the finger (up to ~1.3 cm
below the skin), hence the larger hand tolerance.
"""

from __future__ import annotations

import numpy as np

from data_schemas.cameras import Camera

HAND_TOLERANCE_M = 0.015
FACE_TOLERANCE_M = 0.008


def project_keypoints(camera: Camera, points: np.ndarray, depth: np.ndarray, tolerance: float
                      ) -> np.ndarray:
    """Rows (u, v, visible) for world points (K, 3) seen through ``camera``.

    Args:
        depth: (H, W) the frame's depth buffer (camera z, metres; 0 = empty).
        tolerance: how far (metres) the surface may lie in front of a point
            that still counts as visible.

    Returns:
        (K, 3) float64: OpenCV pixel coordinates
        and 1.0 / 0.0 visibility.
    """
    uv, z = camera.project(points)
    col = np.floor(uv[:, 0] + 0.5).astype(np.int64)  # OpenCV: pixel j spans [j - 0.5, j + 0.5)
    row = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    inside = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    surface = np.zeros_like(z)
    surface[inside] = depth[row[inside], col[inside]]
    unoccluded = (surface <= 0) | (z <= surface + tolerance)
    return np.column_stack([uv, (inside & unoccluded).astype(np.float64)])
