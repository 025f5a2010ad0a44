"""Square crops: the adjusted intrinsics agree with where the resampled image puts things."""

from __future__ import annotations

import numpy as np
import pytest

from avatar.preprocess.crops import SquareCrop, label_box, square_crop, union_box
from avatar.preprocess.masks import background_colour, key_foreground


def _blob(h: int, w: int, cx: float, cy: float, sigma: float) -> np.ndarray:
    """A Gaussian blob centred at continuous OpenCV coordinates (cx, cy)."""
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    return np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))


def _centroid(img: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    return np.array([(xx * img).sum(), (yy * img).sum()]) / img.sum()


@pytest.mark.parametrize(("x0", "y0", "size", "out"), [(10, 20, 80, 40), (-8, 5, 90, 120), (30, 20, 50, 50)])
def test_intrinsics_follow_the_resampled_image(x0, y0, size, out):
    K = np.array([[150.0, 0, 61.3], [0, 150.0, 47.9], [0, 0, 1]])
    point = np.array([0.02, -0.01, 1.0])  # camera-space point
    uv = (K @ point)[:2] / point[2]
    crop = SquareCrop(x0=x0, y0=y0, size=size, out=out)
    image = _blob(120, 130, uv[0], uv[1], sigma=4.0).astype(np.float32)
    cropped = crop.apply(image, 0.0)
    Kc = crop.adjust_intrinsics(K)
    uv_crop = (Kc @ point)[:2] / point[2]
    # Centroid of the resampled blob lands where the crop intrinsics project the point.
    np.testing.assert_allclose(_centroid(cropped), uv_crop, atol=0.05)
    np.testing.assert_allclose(crop.map_points(uv), uv_crop, atol=1e-9)


def test_crop_outside_the_image_pads_with_fill():
    img = np.full((10, 10, 3), 200, np.uint8)
    out = SquareCrop(x0=-5, y0=-5, size=10, out=10).apply(img, np.array([1, 2, 3], np.uint8))
    assert (out[:5, :5] == [1, 2, 3]).all() and (out[5:, 5:] == 200).all()
    far = SquareCrop(x0=100, y0=100, size=4, out=4).apply(img, 7)
    assert (far == 7).all()


def test_label_crop_never_invents_labels():
    labels = np.zeros((40, 40), np.uint8)
    labels[5:20, 5:20] = 1
    labels[18:30, 18:30] = 2
    out = SquareCrop(0, 0, 40, 17).apply(labels, 0, labels=True)
    assert set(np.unique(out)) <= {0, 1, 2}


def test_boxes_and_square_crop():
    labels = np.zeros((50, 60), np.uint8)
    labels[10:20, 30:45] = 2
    np.testing.assert_array_equal(label_box(labels, 2), [30, 10, 45, 20])
    assert label_box(labels, 1) is None
    np.testing.assert_array_equal(union_box([np.array([0, 5, 10, 20.0]), np.array([3, 1, 7, 30.0])]), [0, 1, 10, 30])
    crop = square_crop(np.array([30, 10, 45, 20.0]), margin=0.0, out=32)
    assert crop.size == 15 and crop.x0 == 30 and crop.y0 == 7
    tiny = square_crop(np.array([5, 5, 5, 5.0]), margin=0.1, out=32)  # degenerate box
    assert tiny.size >= 8


def test_keyed_foreground_on_plain_background():
    frames = np.full((2, 20, 20, 3), 128, np.uint8)
    frames[:, 5:10, 5:10] = (200, 150, 120)
    bg = background_colour(frames)
    np.testing.assert_array_equal(bg, [128, 128, 128])
    mask = key_foreground(frames, bg, threshold=30)
    assert mask.sum() == 2 * 25 and mask[0, 7, 7] == 1
