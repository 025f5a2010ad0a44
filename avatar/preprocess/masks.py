"""Foreground masks when a capture has none: keying against a plain studio background."""

from __future__ import annotations

import numpy as np


def background_colour(frames: np.ndarray, border: int = 2) -> np.ndarray:
    """Median colour (3,) of the image borders over all frames (T, H, W, 3) uint8."""
    edges = np.concatenate([
        frames[:, :border].reshape(-1, 3), frames[:, -border:].reshape(-1, 3),
        frames[:, :, :border].reshape(-1, 3), frames[:, :, -border:].reshape(-1, 3),
    ])
    return np.median(edges, axis=0)


def key_foreground(frames: np.ndarray, background: np.ndarray, threshold: float) -> np.ndarray:
    """(T, H, W) uint8 mask, 1 where a pixel differs from ``background`` by more than ``threshold``
    (Euclidean distance in 8-bit RGB)."""
    dist = np.linalg.norm(frames.astype(np.float32) - background.astype(np.float32), axis=-1)
    return (dist > threshold).astype(np.uint8)
