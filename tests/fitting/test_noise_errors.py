"""Detector corruption and error metrics."""

from __future__ import annotations

import numpy as np

from avatar.fitting.errors import landmark_error, mpjpe, per_vertex_error
from avatar.fitting.noise import corrupt_keypoints


def test_corruption_statistics() -> None:
    uvc = np.tile(np.array([50.0, 40.0, 1.0]), (200, 21, 1))
    uvc[:, 0, 2] = 0.0
    out = corrupt_keypoints(uvc, 1.0, 0.1, 0.1, (96, 80), np.random.default_rng(0))
    assert out.shape == uvc.shape and np.isfinite(out).all()
    assert (out[:, 0, 2] == 0).all()
    dropped = out[:, 1:, 2] == 0
    assert 0.07 < dropped.mean() < 0.13
    far = np.linalg.norm(out[..., :2] - uvc[..., :2], axis=-1) > 6
    assert 0.07 < far[:, 1:].mean() < 0.13
    assert (out[..., 0] >= -0.5).all() and (out[far][:, 0] < 95.5).all() and (out[far][:, 1] < 79.5).all()
    near = out[..., :2][~far] - uvc[..., :2][~far]
    assert abs(near.std() - 1.0) < 0.05


def test_errors_in_millimetres() -> None:
    gt = np.zeros((2, 5, 3))
    pred = gt.copy()
    pred[..., 0] = 0.002
    assert np.isclose(mpjpe(pred, gt), 2.0)
    assert np.isclose(landmark_error(pred, gt), 2.0)
    np.testing.assert_allclose(per_vertex_error(pred, gt), np.full((2, 5), 2.0))
