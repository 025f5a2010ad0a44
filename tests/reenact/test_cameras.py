"""Reenactment cameras against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from avatar.reenact.cameras import framed_intrinsics, look_at, orbit, orbit_intrinsics


def _project(K: np.ndarray, w2c: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    return cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2]


def test_look_at_is_a_rigid_camera_facing_the_target_with_up_pointing_up():
    eye, target, up = np.array([0.3, 0.1, -1.0]), np.array([0.0, 0.05, 0.2]), np.array([0.0, 1.0, 0.0])
    w2c = look_at(eye, target, up)
    R = w2c[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    cam_target = R @ target + w2c[:3, 3]
    np.testing.assert_allclose(cam_target[:2], 0.0, atol=1e-12)
    assert cam_target[2] == pytest.approx(np.linalg.norm(target - eye))
    above = R @ (target + 0.1 * up) + w2c[:3, 3]
    assert above[1] < 0  # image y points down, so "up" is negative y
    with pytest.raises(ValueError, match="parallel"):
        look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]), up)


def test_orbit_circles_the_target_at_a_constant_distance_starting_at_the_eye():
    eye, target, up = np.array([0.0, 0.2, -1.0]), np.array([0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    cams = orbit(eye, target, up, 8)
    centres = np.array([-c[:3, :3].T @ c[:3, 3] for c in cams])
    np.testing.assert_allclose(centres[0], eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(centres - target, axis=1), np.linalg.norm(eye - target), atol=1e-12)
    np.testing.assert_allclose(centres[:, 1], eye[1], atol=1e-12)  # heights kept: a turn about the up axis
    np.testing.assert_allclose(centres[4], [0.0, 0.2, 1.0], atol=1e-12)  # half a turn: the other side
    K = orbit_intrinsics(1.0, 0.25, 64)
    for c in cams:  # the target projects to the image centre, a sphere of the radius fills the image
        np.testing.assert_allclose(_project(K, c, target[None])[0], [31.5, 31.5], atol=1e-9)


def test_framed_intrinsics_keep_every_point_inside_the_crop():
    rng = np.random.default_rng(0)
    points = rng.normal(0, 0.1, (200, 3)) + [0.0, 0.0, 1.5]
    K = np.array([[800.0, 0, 640], [0, 800.0, 360], [0, 0, 1]])
    w2c = np.eye(4)
    Kc = framed_intrinsics(K, w2c, points, 128, margin=0.1)
    uv = _project(Kc, w2c, points)
    assert (uv >= -0.5).all() and (uv <= 127.5).all()
    span = uv.max(0) - uv.min(0)
    assert span.max() == pytest.approx(128 / 1.2, rel=0.02)  # the larger side fills the crop but the margin
    with pytest.raises(ValueError, match="behind"):
        framed_intrinsics(K, w2c, points - [0.0, 0.0, 3.0], 128)


def test_reframe_moves_a_projected_point_to_where_the_new_intrinsics_put_it():
    """A bright pixel at a point's projection under K_from lands at its projection under K_to."""
    from avatar.reenact.cameras import reframe

    K_from = np.array([[300.0, 0, 100.0], [0, 300.0, 80.0], [0, 0, 1]])
    w2c = np.eye(4)
    point = np.array([[0.02, -0.03, 1.0]])
    u, v = np.round(_project(K_from, w2c, point)[0]).astype(int)
    image = np.zeros((160, 200, 3), np.uint8)
    image[v, u] = 255
    # a crop around the point, magnified 2x: K_to = S K_from with a shift; use the exact pixel centre
    K_to = np.array([[600.0, 0, 2 * 100.0 - 2 * u + 32], [0, 600.0, 2 * 80.0 - 2 * v + 32], [0, 0, 1]])
    out = reframe(image, K_from, K_to, 64, background=(0.0, 0.0, 0.0))
    assert out.shape == (64, 64, 3)
    peak = np.unravel_index(out[..., 0].argmax(), out.shape[:2])
    assert peak == (32, 32) and out[32, 32, 0] == 255
    np.testing.assert_array_equal(reframe(image, K_from, K_from, 64, (0.0, 0.0, 0.0)), image[:64, :64])
    outside = reframe(image, K_from, K_to - np.array([[0, 0, 5000.0], [0, 0, 0], [0, 0, 0]]), 16)
    assert (outside == 255).all()  # nothing of the source in view: the background
