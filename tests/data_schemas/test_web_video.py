"""Browser-playable videos: H.264 in MP4, the frames come back, bad input fails cleanly."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from data_schemas.tables import SchemaError
from data_schemas.web_video import read_web_video, write_web_video


def _frames(count: int, height: int, width: int) -> np.ndarray:
    """A moving gradient with a square: smooth content an encoder keeps well."""
    y, x = np.mgrid[0:height, 0:width]
    out = []
    for t in range(count):
        image = np.stack([(x + 4 * t) % 256, y % 256, np.full_like(x, 128)], axis=-1).astype(np.uint8)
        image[10 + t : 30 + t, 20:40] = 255
        out.append(image)
    return np.stack(out)


def test_h264_mp4_round_trip_keeps_frames_rate_and_size(tmp_path):
    frames = _frames(12, 64, 96)
    path = tmp_path / "clip.mp4"
    assert write_web_video(path, frames, 24.0) == 12
    decoded, codec, fps = read_web_video(path)
    assert codec == "h264" and fps == pytest.approx(24.0)
    assert decoded.shape == frames.shape
    mse = np.mean((decoded.astype(np.float64) - frames) ** 2)
    assert 10 * np.log10(255**2 / mse) > 35.0  # crf 18: visually lossless
    with open(path, "rb") as f:  # +faststart: the index (moov) precedes the media data (mdat)
        head = f.read()
    assert head.index(b"moov") < head.index(b"mdat")


def test_odd_sizes_are_padded_to_even(tmp_path):
    path = tmp_path / "odd.mp4"
    write_web_video(path, _frames(3, 33, 45), 10.0)
    decoded, _, _ = read_web_video(path)
    assert decoded.shape == (3, 34, 46, 3)


def test_bad_input_is_one_clear_error_and_leaves_nothing(tmp_path):
    path = tmp_path / "bad.mp4"
    with pytest.raises(SchemaError, match="no frames"):
        write_web_video(path, [], 10.0)
    with pytest.raises(SchemaError, match="frame 1 is"):
        write_web_video(path, [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 10, 3), np.uint8)], 10.0)
    with pytest.raises(SchemaError, match="frame rate"):
        write_web_video(path, _frames(2, 8, 8), 0.0)
    assert list(tmp_path.iterdir()) == []


def test_the_same_frames_give_the_same_bytes_every_time(tmp_path):
    """The cache certifies stages by their outputs' hashes, so an encode must not depend on heap state."""
    frames = _frames(12, 130, 98)  # a size at which x264's mbtree gave 7 distinct files in 20 encodes
    digests = set()
    for attempt in range(12):
        churn = [np.empty(int(n)) for n in np.random.default_rng(attempt).integers(1, 200_000, 50)]
        path = tmp_path / f"clip{attempt}.mp4"
        write_web_video(path, frames, 24.0)
        digests.add(hashlib.sha256(path.read_bytes()).hexdigest())
        del churn
    assert len(digests) == 1
