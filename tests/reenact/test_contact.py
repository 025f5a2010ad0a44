"""The contact-preserving placement's geometry against closed forms: triangle frames, surface twins (round trip,
rigid equivariance, a scaled face), the hand placement on an unchanged face (identity) and on a moved face."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from avatar.reenact.contact import NEAR_M, place_hand, surface_twins, triangle_frames, twin_points

SPHERE = trimesh.creation.icosphere(3, radius=0.08)
FACE, FACES = np.array(SPHERE.vertices), np.array(SPHERE.faces)


def _near_points(count: int, seed: int) -> np.ndarray:
    """(count, 3) points within 1 cm of the sphere's surface, on both sides."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return direction * (0.08 + rng.uniform(-0.01, 0.01, (count, 1)))


def test_triangle_frames_are_right_handed_and_orthonormal_with_the_outward_normal() -> None:
    frames = triangle_frames(FACE, FACES)
    np.testing.assert_allclose(frames.transpose(0, 2, 1) @ frames, np.broadcast_to(np.eye(3), frames.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    centroids = FACE[FACES].mean(1)
    assert ((frames[:, :, 2] * centroids).sum(1) > 0).all()  # outward on a sphere


def test_twins_round_trip_and_follow_a_rigid_motion_of_the_face() -> None:
    points = _near_points(200, 0)
    twins = surface_twins(points, FACE, FACES)
    np.testing.assert_allclose(twin_points(twins, FACE, FACES), points, atol=1e-12)
    np.testing.assert_allclose(twins.distance, np.abs(np.linalg.norm(points, axis=1) - 0.08), atol=5e-4)  # facets
    inside = np.linalg.norm(points, axis=1) < 0.0795
    assert (twins.local[inside, 2] < 0).all() and (twins.local[np.linalg.norm(points, axis=1) > 0.0805, 2] > 0).all()
    R, t = Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix(), np.array([0.1, -0.2, 0.05])
    np.testing.assert_allclose(twin_points(twins, FACE @ R.T + t, FACES), points @ R.T + t, atol=1e-12)


def test_twins_on_a_larger_face_keep_their_offset_from_the_surface() -> None:
    points = _near_points(50, 1)
    twins = surface_twins(points, FACE, FACES)
    moved = twin_points(twins, 1.2 * FACE, FACES)
    # the surface point scales with the face, the offset along the normal does not
    np.testing.assert_allclose(
        np.linalg.norm(moved, axis=1) - 1.2 * 0.08, np.linalg.norm(points, axis=1) - 0.08, atol=5e-4
    )


def _hand(centre: np.ndarray) -> np.ndarray:
    """(Vh, 3) a small box of points, a stand-in hand, around ``centre`` (3,)."""
    grid = np.stack(np.meshgrid(*[np.linspace(-0.01, 0.01, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return grid * [1.0, 1.0, 4.0] + centre


def test_placing_on_the_same_face_changes_nothing_and_far_hands_are_left_alone() -> None:
    hand = _hand(np.array([0.0, 0.0, 0.0805 + 0.04]))  # lowest points 0.5 mm off the top of the sphere
    fix = place_hand(hand, FACE, hand, FACE, FACES)
    np.testing.assert_allclose(fix.rotation, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(fix.translation, 0.0, atol=1e-9)
    assert fix.touching > 0 and fix.kept == fix.touching and fix.residual_m < 1e-9
    far = _hand(np.array([0.0, 0.0, 0.08 + NEAR_M + 0.05]))
    assert place_hand(far, FACE, far, FACE, FACES).matched == 0


@pytest.mark.parametrize("scale", [0.9, 1.25])
def test_a_hand_resting_on_the_face_rests_on_a_scaled_face(scale: float) -> None:
    """The driver's hand rests 0.5 mm above the top of the sphere; the target's face is the sphere scaled and the
    target's hand starts where the driver's was: the placement moves it onto the new top, 0.5 mm above it."""
    hand = _hand(np.array([0.0, 0.0, 0.0805 + 0.04]))
    fix = place_hand(hand, FACE, hand, scale * FACE, FACES)
    moved = hand @ fix.rotation.T + fix.translation
    assert moved[:, 2].min() == pytest.approx(scale * 0.08 + 0.0005, abs=6e-4)  # the facets and the fit
    np.testing.assert_allclose(moved[:, :2].mean(0), 0.0, atol=1e-4)
    assert fix.touching > 0 and fix.kept >= 0.6 * fix.touching  # a flat box on a sphere of another curvature
