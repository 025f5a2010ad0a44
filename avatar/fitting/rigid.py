"""Rigid initialisation: Kabsch alignment of template keypoints to triangulated points."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

MIN_RIGID_POINTS = 3


def kabsch(source: np.ndarray, target: np.ndarray, weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) and translation t (3,) minimising sum w |R source + t - target|^2.

    Args: source, target (N, 3) metres with N >= 3; weight (N,) non-negative (default ones).
    """
    w = np.ones(len(source)) if weight is None else np.asarray(weight, np.float64)
    w = w / max(w.sum(), 1e-12)
    mu_s, mu_t = w @ source, w @ target
    cov = (target - mu_t).T @ ((source - mu_s) * w[:, None])
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    R = u @ np.diag([1.0, 1.0, d]) @ vt
    return R, mu_t - R @ mu_s


def smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of least angle taking direction ``a`` (3,) to direction ``b`` (3,)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        ortho = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])  # 180 degrees about any axis normal to a
        return Rotation.from_rotvec(np.pi * ortho / np.linalg.norm(ortho)).as_matrix()
    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()


def rigid_init(
    rest: np.ndarray, root: np.ndarray, targets: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame global rotation and translation of a template rotating about ``root``.

    The posed template is ``R (x - root) + root + transl``, as in the MANO/FLAME layers.

    Args:
        rest: (K, 3) template keypoints in rest pose (metres).
        root: (3,) the root joint the global rotation turns about.
        targets: (T, K, 3) triangulated keypoints; valid: (T, K) bool.

    Returns:
        global_orient (T, 3) axis-angle, transl (T, 3), ok (T,) frames with >= 3
        valid points. Frames that are not ok copy the nearest ok frame (the
        previous one on ties: frame-to-frame warm start), or stay at identity if
        no frame is ok.
    """
    T = targets.shape[0]
    orient, transl, ok = np.zeros((T, 3)), np.zeros((T, 3)), np.zeros(T, bool)
    for t in range(T):
        use = valid[t]
        if use.sum() < MIN_RIGID_POINTS:
            continue
        R, shift = kabsch(rest[use], targets[t, use])
        orient[t] = Rotation.from_matrix(R).as_rotvec()
        transl[t] = shift + R @ root - root
        ok[t] = True
    fill_from_nearest(ok, orient, transl)
    return orient, transl, ok


def fill_from_nearest(ok: np.ndarray, *rows: np.ndarray) -> None:
    """In place: every frame that is not ``ok`` (T,) copies, in each of ``rows``
    (T, ...), the nearest ok frame (the previous one on ties: frame-to-frame
    warm start). Nothing changes when no frame is ok."""
    good = np.flatnonzero(ok)
    if not good.size:
        return
    for t in np.flatnonzero(~ok):
        nearest = good[np.argmin(np.abs(good - t) * 2 - (good < t))]
        for values in rows:
            values[t] = values[nearest]
