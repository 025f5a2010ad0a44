"""Ground-truth 2D keypoints: projection plus an in-image and occlusion test.

A keypoint counts as visible, as a 2D detector would report it, when it
projects inside the image and is not hidden:

- by *another* part (the hand in front of a face landmark, the face in front
  of a hand joint) nearer than ``OTHER_PART_TOLERANCE_M``; or
- by its own part by more than a self-occlusion tolerance. Hand keypoints are
  mostly joint centres, which lie inside the hand (the wrist up to ~2.5 cm below
  the skin), and detectors infer self-occluded joints from the rest of the hand,
  so the hand's tolerance is a hand's thickness; face landmarks lie on the skin,
  and the tolerance only hides those behind the nose or the far cheek.

An earlier version hid every keypoint more than 1.5 cm behind *any* surface,
which hid the wrist in every view and left contact frames with too few
keypoints to fit: no detector behaves like that.
"""

from __future__ import annotations

import numpy as np

from data_schemas.cameras import Camera

HAND_SELF_TOLERANCE_M = 0.04
FACE_SELF_TOLERANCE_M = 0.02
OTHER_PART_TOLERANCE_M = 0.005


def project_keypoints(
    camera: Camera,
    points: np.ndarray,
    depth: np.ndarray,
    labels: np.ndarray,
    own_label: int,
    self_tolerance: float,
    other_tolerance: float = OTHER_PART_TOLERANCE_M,
) -> np.ndarray:
    """Rows (u, v, visible) for world points (K, 3) of one part seen through ``camera``.

    Args:
        depth: (H, W) the frame's depth buffer (camera z, metres; 0 = empty).
        labels: (H, W) the part label of the surface in each pixel (0 = empty).
        own_label: the label of the part the points belong to.
        self_tolerance: how far (metres) the part's own surface may lie in
            front of a point that still counts as visible.
        other_tolerance: the same for any other part's surface.

    Returns:
        (K, 3) float64: OpenCV pixel coordinates and 1.0 / 0.0 visibility.
    """
    uv, z = camera.project(points)
    col = np.floor(uv[:, 0] + 0.5).astype(np.int64)  # OpenCV: pixel j spans [j - 0.5, j + 0.5)
    row = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    inside = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    surface = np.zeros_like(z)
    surface[inside] = depth[row[inside], col[inside]]
    label = np.zeros(len(z), np.int64)
    label[inside] = labels[row[inside], col[inside]]
    tolerance = np.where(label == own_label, self_tolerance, other_tolerance)
    unoccluded = (surface <= 0) | (z <= surface + tolerance)
    return np.column_stack([uv, (inside & unoccluded).astype(np.float64)])
