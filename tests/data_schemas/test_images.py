"""``to_uint8``: the one float-to-uint8 conversion of renders, against the closed form."""

from __future__ import annotations

import numpy as np

from data_schemas.images import to_uint8


def test_to_uint8_rounds_half_up_and_clips() -> None:
    values = np.array([-0.2, 0.0, 0.49 / 255, 0.5 / 255, 1 / 255, 127.5 / 255, 0.999, 1.0, 1.3])
    expected = np.array([0, 0, 0, 1, 1, 128, 255, 255, 255], dtype=np.uint8)
    np.testing.assert_array_equal(to_uint8(values), expected)
    image = np.random.default_rng(0).uniform(-0.5, 1.5, size=(4, 5, 3)).astype(np.float32)
    out = to_uint8(image)
    assert out.shape == image.shape and out.dtype == np.uint8
    np.testing.assert_array_equal(out, np.floor(np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
