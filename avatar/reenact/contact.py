"""Contact-preserving hand placement for motion transfer: a finger on the driver's cheek lands on the target's cheek.

The face topology is shared, so a point near the driver's face has a twin near the target's face: the same
triangle, the same barycentric coordinates of its closest surface point, the same offset from that point in
the triangle's local frame (origin at the closest point, axes from the first edge and the normal, as
GaussianAvatars binds a Gaussian). Per frame (:func:`place_hand`):

1. every driver hand vertex within ``NEAR_M`` of the driver's face (the paper's interaction radius d_max)
   gets its twin on the target's face and a weight ``w = (cos(pi d / NEAR_M) + 1) / 2`` of its distance ``d``
   (1 in contact, 0 at ``NEAR_M``: the paper's interaction weight);
2. one rigid motion of the target's hand (as the scaled transform placed it) minimises
   ``sum_k w_k |R h_k + t - q_k|^2 + ANCHOR_WEIGHT sum_j |R h_j + t - h_j|^2`` (weighted Kabsch): the twins
   pull the touching points onto the same surface points, the anchor term keeps what they do not determine
   (the rotation about a single fingertip) and makes the correction fade smoothly to nothing as the hand
   leaves the face;
3. where that leaves the target's hand deeper inside the target's face than the driver's hand was in its own,
   the hand moves out along the contact's normal until it is not;
4. a frame with no hand vertex within ``NEAR_M`` of the face is placed exactly as by the scaled transform.

Penetration is the driver's: a twin keeps its point's signed offset from the surface, so a finger pressing
3 mm into the driver's cheek presses 3 mm into the target's, and the contact simulation dents it alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar.fitting.rigid import kabsch, smallest_rotation
from avatar.pbd.collision import closest_on_mesh

#: Hand vertices nearer the face than this (metres) are matched to it: the paper's interaction radius d_max.
NEAR_M = 0.05
#: Hand vertices nearer than this (metres) are reported as touching.
TOUCH_M = 0.002
#: Weight per hand vertex of staying where the scaled transform put it (relative to a touching twin's 1).
ANCHOR_WEIGHT = 0.02
#: The corrected hand may lie this much deeper inside the target's face than the driver's did (metres) ...
PUSH_TOLERANCE_M = 1e-4
#: ... after at most this many pushes out along the contact normal.
PUSH_ROUNDS = 5
#: A driver's hand vertex deeper than this inside its own face (metres) means the hand passes through it.
PASS_THROUGH_M = 0.015


@dataclass(frozen=True)
class SurfaceTwins:
    """Where points (N,) sit relative to a face mesh: ``triangle`` (N,) int64, ``barycentric`` (N, 3) of the
    closest surface point, ``local`` (N, 3) offset from it in the triangle's frame (metres; z along the outward
    normal, negative inside), ``distance`` (N,) to the surface (metres)."""

    triangle: np.ndarray
    barycentric: np.ndarray
    local: np.ndarray
    distance: np.ndarray


def triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3, 3) orthonormal frames of the triangles (columns: first edge, normal x edge, outward normal)."""
    tri = vertices[faces]
    edge = tri[:, 1] - tri[:, 0]
    normal = np.cross(edge, tri[:, 2] - tri[:, 0])
    x = edge / np.maximum(np.linalg.norm(edge, axis=1, keepdims=True), 1e-300)
    z = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    return np.stack([x, np.cross(z, x), z], axis=2)


def _barycentric(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of points (N, 3) on their triangles (N, 3, 3) (least squares)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    denom = np.where(np.abs(d00 * d11 - d01 * d01) > 1e-300, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    return np.stack([1.0 - v - w, v, w], axis=1)


def surface_twins(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> SurfaceTwins:
    """Where ``points`` (N, 3) sit relative to the face mesh ``vertices`` (V, 3), ``faces`` (F, 3)."""
    closest_t, distance, triangle_t = closest_on_mesh(
        torch.from_numpy(points), torch.from_numpy(vertices), torch.from_numpy(np.array(faces, dtype=np.int64))
    )
    closest, triangle = closest_t.numpy(), triangle_t.numpy()
    frames = triangle_frames(vertices, faces)[triangle]
    local = np.einsum("nji,nj->ni", frames, points - closest)
    return SurfaceTwins(triangle, _barycentric(closest, vertices[faces[triangle]]), local, distance.numpy())


def twin_points(twins: SurfaceTwins, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) the points that sit on the face mesh ``vertices`` (V, 3) as ``twins`` sat on theirs."""
    surface = np.einsum("nk,nkj->nj", twins.barycentric, vertices[faces[twins.triangle]])
    return surface + np.einsum("nij,nj->ni", triangle_frames(vertices, faces)[twins.triangle], twins.local)


@dataclass(frozen=True)
class Placement:
    """One frame's correction of the target's hand: ``rotation`` (3, 3) and ``translation`` (3,) applied to the
    scaled transform's hand (world); the hand vertices matched to the face (``matched``, weight > 0); those
    touching the driver's face (``touching``: within :data:`TOUCH_M` of it or inside it) and how many of them
    touch the target's face after the correction (``kept``); the touching points' mean distance from their
    twins, the same surface points of the target's face (``residual_m``, 0 without touch); and the driver's
    deepest hand vertex inside its own face (``driver_depth_m``, 0 when none)."""

    rotation: np.ndarray
    translation: np.ndarray
    matched: int
    touching: int
    kept: int
    residual_m: float
    driver_depth_m: float


def place_hand(
    driver_hand: np.ndarray,
    driver_face: np.ndarray,
    target_hand: np.ndarray,
    target_face: np.ndarray,
    faces: np.ndarray,
) -> Placement:
    """The rigid correction that puts the target's hand (Vh, 3) (as the scaled transform placed it) on the target's
    face (V, 3) where the driver's hand (Vh, 3) touches the driver's face (V, 3); identity when the driver's hand
    is nowhere within :data:`NEAR_M` of its face."""
    lo, hi = driver_face.min(0) - NEAR_M, driver_face.max(0) + NEAR_M
    candidates = np.flatnonzero(((driver_hand >= lo) & (driver_hand <= hi)).all(1))
    identity = Placement(np.eye(3), np.zeros(3), 0, 0, 0, 0.0, 0.0)
    if candidates.size == 0:
        return identity
    twins = surface_twins(driver_hand[candidates], driver_face, faces)
    near = twins.distance < NEAR_M
    if not near.any():
        return identity
    keep = candidates[near]
    twins = SurfaceTwins(twins.triangle[near], twins.barycentric[near], twins.local[near], twins.distance[near])
    weight = (np.cos(np.pi * twins.distance / NEAR_M) + 1.0) / 2.0
    goal = twin_points(twins, target_face, faces)
    # Turn the hand with the touched surface (its mean normal, driver's to target's) about the contact, as far as
    # the hand is close (the largest weight), then let the twins pull the touching points onto their places.
    normal = weight @ triangle_frames(target_face, faces)[twins.triangle, :, 2]  # the contact's, on the target
    turn = _partial(
        smallest_rotation(weight @ triangle_frames(driver_face, faces)[twins.triangle, :, 2], normal),
        float(weight.max()),
    )
    pivot = weight @ goal / weight.sum()
    turned = (target_hand - pivot) @ turn.T + pivot
    source = np.concatenate([turned[keep], turned])
    target = np.concatenate([goal, turned])
    weights = np.concatenate([weight, np.full(len(target_hand), ANCHOR_WEIGHT)])
    rotation, translation = kabsch(source, target, weights)
    rotation, translation = rotation @ turn, rotation @ (pivot - turn @ pivot) + translation
    allowed = max(0.0, -float(twins.local[:, 2].min()))  # the driver's own press
    translation = translation + _push_out(
        target_hand @ rotation.T + translation, target_face, faces, allowed, normal / np.linalg.norm(normal)
    )
    touching = twins.local[:, 2] < TOUCH_M  # within TOUCH_M above the driver's face, or below it
    moved = target_hand[keep[touching]] @ rotation.T + translation
    miss = np.linalg.norm(moved - goal[touching], axis=1)
    kept = int((surface_twins(moved, target_face, faces).local[:, 2] < TOUCH_M).sum()) if moved.size else 0
    return Placement(
        rotation,
        translation,
        int(keep.size),
        int(touching.sum()),
        kept,
        float(miss.mean()) if miss.size else 0.0,
        allowed,
    )


def _push_out(hand: np.ndarray, face: np.ndarray, faces: np.ndarray, allowed: float, normal: np.ndarray) -> np.ndarray:
    """(3,) translation along the unit ``normal`` (3,) that brings the hand (Vh, 3) no deeper inside the face
    (V, 3) than ``allowed`` metres (measured along each nearest triangle's normal, within :data:`NEAR_M`)."""
    shift = np.zeros(3)
    lo, hi = face.min(0) - NEAR_M, face.max(0) + NEAR_M
    near = np.flatnonzero(((hand >= lo) & (hand <= hi)).all(1))
    for _ in range(PUSH_ROUNDS):
        if near.size == 0:
            break
        twins = surface_twins(hand[near] + shift, face, faces)
        depth = -twins.local[twins.distance < NEAR_M, 2]
        excess = float(depth.max(initial=0.0)) - allowed
        if excess <= PUSH_TOLERANCE_M:
            break
        shift = shift + (excess + PUSH_TOLERANCE_M) * normal
    return shift


def _partial(rotation: np.ndarray, fraction: float) -> np.ndarray:
    """(3, 3) ``rotation`` (3, 3) about its axis by ``fraction`` of its angle."""
    return Rotation.from_rotvec(fraction * Rotation.from_matrix(rotation).as_rotvec()).as_matrix()
