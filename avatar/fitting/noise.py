"""Synthetic detector corruption for the ground-truth keypoint backend."""

from __future__ import annotations

import numpy as np


def corrupt_keypoints(
    uvc: np.ndarray,
    pixel_noise: float,
    drop_rate: float,
    outlier_rate: float,
    image_size: tuple[int, int] | int,
    rng: np.random.Generator,
) -> np.ndarray:
    """A noisy copy of clean detections.

    Args:
        uvc: (..., K, 3) rows (u, v, confidence), OpenCV pixels.
        pixel_noise: standard deviation (px) of the Gaussian added to u and v.
        drop_rate: probability that a detection is dropped (confidence 0).
        outlier_rate: probability that a confident detection moves to a uniform
            random position in the image, keeping its confidence.
        image_size: (width, height) or one side of a square image, px.
        rng: the random source.

    Returns:
        (..., K, 3) float64; undetected keypoints (confidence 0) stay undetected.
    """
    # isinstance narrows the type of the tuple branch; np.isscalar also takes numpy and float scalars
    if isinstance(image_size, int) or np.isscalar(image_size):
        width, height = image_size, image_size
    else:
        width, height = image_size
    out = np.array(uvc, dtype=np.float64, copy=True)
    shape = out.shape[:-1]
    out[..., :2] += rng.normal(0.0, pixel_noise, size=(*shape, 2))
    outlier = (rng.random(shape) < outlier_rate) & (out[..., 2] > 0)
    random_uv = rng.random((*shape, 2)) * np.array([width, height]) - 0.5
    out[..., :2] = np.where(outlier[..., None], random_uv, out[..., :2])
    out[..., 2] = np.where(rng.random(shape) < drop_rate, 0.0, out[..., 2])
    return out
