"""Part boxes from label masks, and square crops with the intrinsics that go with them.

Pixel convention: OpenCV's, pixel (i, j) has its centre at continuous
coordinates (x=j, y=i). A crop takes the square ``[x0, x0+size) x [y0, y0+size)``
of pixels and resamples it to ``out`` pixels (area averaging), so a continuous
point x maps to ``(x - x0 + 0.5) * s - 0.5`` with ``s = out / size``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SquareCrop:
    """A square window of a camera image. ``x0``, ``y0`` may be negative (padding)."""

    x0: int
    y0: int
    size: int
    out: int

    @property
    def scale(self) -> float:
        return self.out / self.size

    def adjust_intrinsics(self, K: np.ndarray) -> np.ndarray:
        """(3, 3) intrinsics of the full image -> (3, 3) intrinsics of the resampled crop."""
        s = self.scale
        Kc = np.array(K, dtype=np.float64, copy=True)
        Kc[0, 0] *= s
        Kc[0, 1] *= s
        Kc[1, 1] *= s
        Kc[0, 2] = (K[0, 2] - self.x0 + 0.5) * s - 0.5
        Kc[1, 2] = (K[1, 2] - self.y0 + 0.5) * s - 0.5
        return Kc

    def map_points(self, uv: np.ndarray) -> np.ndarray:
        """Full-image pixel coordinates (..., 2) -> crop pixel coordinates (..., 2)."""
        offset = np.array([self.x0, self.y0], dtype=np.float64)
        return (np.asarray(uv, dtype=np.float64) - offset + 0.5) * self.scale - 0.5

    def apply(self, image: np.ndarray, fill: np.ndarray | int, labels: bool = False) -> np.ndarray:
        """Cut and resample ``image`` ((H, W) or (H, W, C)); outside pixels take ``fill``.

        Label images are resampled by nearest neighbour so no label is invented.
        """
        h, w = image.shape[:2]
        pad_shape = (self.size, self.size) + image.shape[2:]
        window = np.empty(pad_shape, dtype=image.dtype)
        window[...] = fill
        ys, xs = max(self.y0, 0), max(self.x0, 0)
        ye, xe = min(self.y0 + self.size, h), min(self.x0 + self.size, w)
        if ye > ys and xe > xs:
            window[ys - self.y0 : ye - self.y0, xs - self.x0 : xe - self.x0] = image[ys:ye, xs:xe]
        if self.size == self.out:
            return window
        interp = cv2.INTER_NEAREST if labels else (cv2.INTER_AREA if self.out < self.size else cv2.INTER_LINEAR)
        return cv2.resize(window, (self.out, self.out), interpolation=interp)


def label_box(labels: np.ndarray, label: int) -> np.ndarray | None:
    """Tight box (x0, y0, x1, y1), exclusive end, of the pixels equal to ``label``; None if there are none."""
    ys, xs = np.nonzero(labels == label)
    if len(xs) == 0:
        return None
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)


def overlap_box(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """Intersection (x0, y0, x1, y1) of two boxes; None when either is None or they do not overlap."""
    if a is None or b is None:
        return None
    box = np.concatenate([np.maximum(a[:2], b[:2]), np.minimum(a[2:], b[2:])])
    return box if (box[2:] > box[:2]).all() else None


def union_box(boxes: list[np.ndarray]) -> np.ndarray:
    """Smallest box containing every box (x0, y0, x1, y1)."""
    stacked = np.stack(boxes)
    return np.concatenate([stacked[:, :2].min(0), stacked[:, 2:].max(0)])


def square_crop(box: np.ndarray, margin: float, out: int, min_size: int = 8) -> SquareCrop:
    """The square around ``box`` (x0, y0, x1, y1) grown by ``margin`` (fraction of its larger side)."""
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    side = max(box[2] - box[0], box[3] - box[1]) * (1 + 2 * margin)
    size = max(int(np.ceil(side)), min_size)
    return SquareCrop(x0=int(np.floor(cx - size / 2)), y0=int(np.floor(cy - size / 2)), size=size, out=out)
