"""Robust multi-view triangulation of 2D keypoints.

Confidence-weighted linear triangulation (DLT) of every keypoint, with RANSAC
over view pairs to reject outlier detections and a final weighted DLT on the
inliers. Missing detections (NaN coordinates, NaN or zero confidence) are
ignored; keypoints seen by fewer than ``min_views`` views come back invalid
with a zero position, never NaN.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations
from typing import Any, NamedTuple

import numpy as np


class Triangulation(NamedTuple):
    """points (K, 3) world metres (zero where invalid); inlier_mask (C, K) the
    detections used for each point; valid (K,) points seen by enough inlier views."""

    points: np.ndarray
    inlier_mask: np.ndarray
    valid: np.ndarray


def projection_matrices(cameras: Sequence[Any] | np.ndarray) -> np.ndarray:
    """(C, 3, 4) pixel projection matrices ``K [R | t]``.

    ``cameras`` is a (C, 3, 4) array, a sequence of ``(K (3, 3), world_to_cam (4, 4))``
    pairs, or a sequence of objects with ``K`` and ``world_to_cam`` attributes
    (:class:`data_schemas.cameras.Camera`).
    """
    if isinstance(cameras, np.ndarray):
        if cameras.ndim != 3 or cameras.shape[1:] != (3, 4):
            raise ValueError(f"projection matrices must be (C, 3, 4), got {cameras.shape}")
        return cameras.astype(np.float64)
    mats = []
    for cam in cameras:
        K, w2c = (cam.K, cam.world_to_cam) if hasattr(cam, "K") else cam
        mats.append(np.asarray(K, np.float64) @ np.asarray(w2c, np.float64)[:3, :4])
    return np.stack(mats) if mats else np.zeros((0, 3, 4))


def clean_observations(uvc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) rows (u, v, confidence) -> uv (..., 2) with NaN replaced by 0 and
    confidence (...,) in [0, 1], zero wherever any entry is not finite."""
    finite = np.isfinite(uvc).all(axis=-1)
    uv = np.where(finite[..., None], uvc[..., :2], 0.0)
    conf = np.where(finite, np.clip(uvc[..., 2], 0.0, 1.0), 0.0)
    return uv, conf


def weighted_dlt(P: np.ndarray, uv: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Linear triangulation of a batch of points.

    Args:
        P: (C, 3, 4) projection matrices.
        uv: (..., C, 2) pixel observations.
        weight: (..., C) non-negative weights (0 drops a view).

    Returns:
        (..., 3) points; the rows of each view are normalised before weighting,
        so a weight acts like an inverse pixel standard deviation. Exact for
        noise-free observations in >= 2 views. Degenerate inputs give finite
        (meaningless) points; callers check the view count.
    """
    rows_u = uv[..., 0, None] * P[:, 2] - P[:, 0]  # (..., C, 4)
    rows_v = uv[..., 1, None] * P[:, 2] - P[:, 1]
    rows = np.stack((rows_u, rows_v), axis=-2)  # (..., C, 2, 4)
    rows = rows / np.maximum(np.linalg.norm(rows, axis=-1, keepdims=True), 1e-12)
    A = (rows * weight[..., None, None]).reshape(*uv.shape[:-2], -1, 4)
    _, _, vh = np.linalg.svd(A)
    X = vh[..., -1, :]
    w = X[..., 3:]
    w = np.where(np.abs(w) < 1e-12, np.copysign(1e-12, w), w)
    return X[..., :3] / w


def reprojection_errors(P: np.ndarray, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel distances (..., C) between ``uv`` (..., C, 2) and the projections of
    ``points`` (..., 3); infinite for points behind a camera."""
    hom = np.concatenate((points, np.ones_like(points[..., :1])), axis=-1)
    proj = np.einsum("cij,...j->...ci", P, hom)  # (..., C, 3)
    z = proj[..., 2]
    safe = np.where(z > 1e-9, z, 1.0)
    err = np.linalg.norm(proj[..., :2] / safe[..., None] - uv, axis=-1)
    return np.where(z > 1e-9, err, np.inf)


def triangulate(
    uvc: np.ndarray,
    cameras: Sequence[Any] | np.ndarray,
    min_views: int = 2,
    ransac_threshold_px: float = 8.0,
    min_confidence: float = 1e-3,
) -> Triangulation:
    """Triangulate K keypoints seen in C views.

    Args:
        uvc: (C, K, 3) rows (u, v, confidence) per view, OpenCV pixels.
        cameras: see :func:`projection_matrices`.
        min_views: inlier views a point needs to be valid (>= 2).
        ransac_threshold_px: reprojection distance (px) under which a detection
            agrees with a hypothesis.
        min_confidence: detections with lower confidence are ignored.

    Every pair of usable views proposes a point (DLT); the proposal with the
    most inliers (ties: the smallest summed truncated error) wins, and the
    point is re-estimated by confidence-weighted DLT on its inliers, whose set
    is then recomputed once.
    """
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2, got {min_views}")
    P = projection_matrices(cameras)
    num_views, num_points = uvc.shape[:2]
    if P.shape[0] != num_views:
        raise ValueError(f"{num_views} views of keypoints but {P.shape[0]} cameras")
    uv, conf = clean_observations(np.asarray(uvc, np.float64))
    uv, conf = uv.transpose(1, 0, 2), conf.T  # (K, C, 2), (K, C)
    usable = conf >= min_confidence
    if num_views < 2:
        return Triangulation(
            np.zeros((num_points, 3)), np.zeros((num_views, num_points), bool), np.zeros(num_points, bool)
        )

    pairs = np.array(list(combinations(range(num_views), 2)))  # (N, 2)
    pair_weight = np.zeros((len(pairs), num_views))
    pair_weight[np.arange(len(pairs))[:, None], pairs] = 1.0
    hyp = weighted_dlt(P, np.broadcast_to(uv, (len(pairs), *uv.shape)), pair_weight[:, None, :])  # (N, K, 3)
    err = reprojection_errors(P, hyp, uv[None])  # (N, K, C)
    agree = (err < ransac_threshold_px) & usable[None]
    score = agree.sum(axis=-1) - np.where(agree, err, ransac_threshold_px).sum(axis=-1) / (
        ransac_threshold_px * (num_views + 1)
    )
    pair_ok = usable[:, pairs[:, 0]].T & usable[:, pairs[:, 1]].T  # (N, K)
    score = np.where(pair_ok, score, -np.inf)
    best = np.argmax(score, axis=0)  # (K,)
    inliers = agree[best, np.arange(num_points)]  # (K, C)

    points = weighted_dlt(P, uv, conf * inliers)
    inliers = (reprojection_errors(P, points, uv) < ransac_threshold_px) & usable & inliers.any(-1, keepdims=True)
    points = weighted_dlt(P, uv, conf * inliers)
    valid = (inliers.sum(axis=-1) >= min_views) & np.isfinite(points).all(axis=-1)
    points = np.where(valid[:, None], points, 0.0)
    return Triangulation(points, (inliers & valid[:, None]).T, valid)
