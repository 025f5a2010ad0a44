"""Foreground masks when a capture has none (keying against a plain studio background), and part
labels from a person matte plus hand keypoints."""

from __future__ import annotations

import cv2
import numpy as np


def background_colour(frames: np.ndarray, border: int = 2) -> np.ndarray:
    """Median colour (3,) of the image borders over all frames (T, H, W, 3) uint8."""
    edges = np.concatenate(
        [
            frames[:, :border].reshape(-1, 3),
            frames[:, -border:].reshape(-1, 3),
            frames[:, :, :border].reshape(-1, 3),
            frames[:, :, -border:].reshape(-1, 3),
        ]
    )
    return np.median(edges, axis=0)


def key_foreground(frames: np.ndarray, background: np.ndarray, threshold: float) -> np.ndarray:
    """(T, H, W) uint8 mask, 1 where a pixel differs from ``background`` by more than ``threshold``
    (Euclidean distance in 8-bit RGB)."""
    dist = np.linalg.norm(frames.astype(np.float32) - background.astype(np.float32), axis=-1)
    return (dist > threshold).astype(np.uint8)


def label_parts(foreground: np.ndarray, hand_points: np.ndarray | None, margin: float) -> np.ndarray:
    """Part labels (H, W) uint8 from a person matte and the hand's 2D keypoints.

    ``foreground`` (H, W) bool; ``hand_points`` (K, 2) pixel positions of the confidently detected hand
    keypoints, or None. Foreground inside the keypoints' convex hull, grown about its centre by
    ``margin`` (a fraction of the hull's size, so it covers the skin around the joints), is hand (2);
    the rest of the foreground is face (1: head, hair, neck, whatever else the matte holds).
    """
    labels = foreground.astype(np.uint8)
    if hand_points is None or len(hand_points) < 3:
        return labels
    points = np.asarray(hand_points, dtype=np.float64)
    centre = points.mean(axis=0)
    grown = centre + (points - centre) * (1.0 + margin)
    hull = cv2.convexHull(np.round(grown).astype(np.int32))
    region = np.zeros(labels.shape, np.uint8)
    cv2.fillConvexPoly(region, hull, 1)
    labels[(region > 0) & foreground] = 2
    return labels
