"""Robust triangulation against exact synthetic projections."""

from __future__ import annotations

import numpy as np

from avatar.fitting.noise import corrupt_keypoints
from avatar.fitting.triangulation import projection_matrices, triangulate
from avatar.synthetic.rig import make_rig


def _scene(num_points: int = 30, seed: int = 0) -> tuple[list, np.ndarray, np.ndarray]:
    """Rig of 7 cameras at 256 px, points (K, 3) near the aim point, exact uvc (C, K, 3)."""
    cams = make_rig(7, 256, np.zeros(3))
    points = np.random.default_rng(seed).uniform(-0.08, 0.08, (num_points, 3))
    uvc = np.stack([np.column_stack([c.project(points)[0], np.ones(num_points)]) for c in cams])
    return cams, points, uvc


def test_exact_projections_recover_points() -> None:
    cams, points, uvc = _scene()
    tri = triangulate(uvc, cams)
    assert tri.valid.all() and tri.inlier_mask.all()
    np.testing.assert_allclose(tri.points, points, atol=1e-6)


def test_camera_formats_agree() -> None:
    cams, points, uvc = _scene(5)
    pairs = [(c.K, c.world_to_cam) for c in cams]
    np.testing.assert_allclose(projection_matrices(pairs), projection_matrices(cams))
    np.testing.assert_allclose(triangulate(uvc, projection_matrices(cams)).points, points, atol=1e-6)


def test_outliers_are_rejected() -> None:
    cams, points, uvc = _scene()
    noisy = corrupt_keypoints(uvc, 0.0, 0.0, 0.2, 256, np.random.default_rng(1))
    moved = np.linalg.norm(noisy[..., :2] - uvc[..., :2], axis=-1) > 8
    tri = triangulate(noisy, cams, ransac_threshold_px=4.0)
    ok = (~moved).sum(0) >= 2
    assert tri.valid[ok].all()
    np.testing.assert_allclose(tri.points[ok], points[ok], atol=1e-6)
    assert not (tri.inlier_mask & moved).any()


def test_nan_and_missing_views_are_ignored() -> None:
    cams, points, uvc = _scene(6)
    uvc[0, 0] = np.nan  # point 0: NaN in view 0
    uvc[1:, 1, 2] = 0.0  # point 1: seen by one view only
    uvc[:, 2] = np.nan  # point 2: seen by no view
    uvc[3, 3, 2] = np.nan  # point 3: NaN confidence in view 3
    tri = triangulate(uvc, cams)
    assert np.isfinite(tri.points).all()
    np.testing.assert_array_equal(tri.valid, [True, False, False, True, True, True])
    np.testing.assert_allclose(tri.points[tri.valid], points[tri.valid], atol=1e-6)
    np.testing.assert_array_equal(tri.points[~tri.valid], 0.0)
    assert not tri.inlier_mask[0, 0] and not tri.inlier_mask[3, 3]
