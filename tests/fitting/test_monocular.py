"""Single-view placement of a part by PnP against its template's rest points."""

from __future__ import annotations

import cv2
import numpy as np

from avatar.fitting.monocular import MIN_PNP_POINTS, PALM, place_rest_points
from data_schemas.cameras import Camera

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])


def _camera() -> Camera:
    w2c = np.eye(4)
    w2c[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    w2c[:3, 3] = [0.02, -0.01, 0.6]
    return Camera("cam", 320, 240, K, w2c, np.zeros(5), "train")


def _rest(n: int = 21) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform(-0.05, 0.05, (n, 3))


def test_noise_free_detections_place_the_rest_points_exactly():
    rest, camera = _rest(), _camera()
    rotations = [cv2.Rodrigues(np.array([0.3 * t, -0.1, 0.2]))[0] for t in range(3)]
    world = np.stack([rest @ R.T + np.array([0.01 * t, 0.0, -0.02]) for t, R in enumerate(rotations)])
    uv, _ = camera.project(world)
    points, valid = place_rest_points(rest, uv, np.ones(uv.shape[:2]), camera, 0.5)
    assert valid.all()
    np.testing.assert_allclose(points, world, atol=1e-7)
    palm_only, valid = place_rest_points(rest, uv, np.ones(uv.shape[:2]), camera, 0.5, PALM)
    assert valid.all()
    np.testing.assert_allclose(palm_only, world, atol=1e-6)  # all 21 placed from the 6 palm points


def test_too_few_confident_points_leave_the_frame_invalid():
    rest, camera = _rest(), _camera()
    uv, _ = camera.project(rest[None])
    conf = np.zeros((1, 21))
    conf[0, list(PALM[: MIN_PNP_POINTS - 1])] = 1.0
    points, valid = place_rest_points(rest, uv, conf, camera, 0.5, PALM)
    assert not valid.any() and not points.any()
    uv_nan = uv.copy()
    uv_nan[0, list(PALM)] = np.nan
    _, valid = place_rest_points(rest, uv_nan, np.ones((1, 21)), camera, 0.5, PALM)
    assert not valid.any()
