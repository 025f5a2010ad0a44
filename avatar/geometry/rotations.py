"""Rotations as the trackers and the trainers compare them."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T,) angle of R(a)^T R(b) for axis-angle rows (T, 3), degrees."""
    return np.degrees((Rotation.from_rotvec(a).inv() * Rotation.from_rotvec(b)).magnitude())
