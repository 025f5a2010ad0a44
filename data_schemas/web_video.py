"""Videos that play in a browser (``<video>`` in Chromium, Firefox, Safari): H.264 (High profile,
yuv420p) in MP4 with the index at the front (``+faststart``), encoded with PyAV's bundled FFmpeg and
libx264. OpenCV's ``mp4v`` (MPEG-4 Part 2, :mod:`data_schemas.video`) does not play in Chromium.

Frames are (H, W, 3) uint8 RGB; odd sizes are padded by one pixel (yuv420p needs even sides). The file
is written next to its destination and renamed into place, so a failed encode leaves nothing.

x264's macroblock tree (``mbtree``) is switched off: with it, the bundled libx264 gave different bytes for
the same frames from one encode to the next at some sizes (4 distinct files in 20 encodes of 56x40, 7 of
98x130), which the cache reports as a non-deterministic stage. Without it every size tried gave one file
in 20. It costs bitrate (files are larger at the same CRF), not quality.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path
from typing import Final

import numpy as np

from data_schemas.tables import SchemaError
from data_schemas.video import checked_frame

CODEC: Final = "libx264"  # Final keeps the literal type, by which PyAV's stubs know add_stream makes a video stream
CRF = 18  # visually lossless for renders; the player needs nothing special


def write_web_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Encode (H, W, 3) uint8 RGB ``frames`` at ``fps`` into a browser-playable MP4; returns the frame count.

    Raises :class:`SchemaError` naming the file on a bad frame rate, frame shape or an empty sequence.
    """
    path = Path(path)
    if not np.isfinite(fps) or fps <= 0:
        raise SchemaError(f"{path}: frame rate must be positive, got {fps}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp.mp4")
    count, size = 0, None
    try:
        import av  # PyAV: only the stages that write videos need it

        with av.open(str(tmp), mode="w", options={"movflags": "+faststart"}) as container:
            stream = None
            for frame in frames:
                frame = checked_frame(path, frame, count, size)
                if stream is None:
                    size = frame.shape[:2]
                    stream = container.add_stream(CODEC, rate=Fraction(fps).limit_denominator(1001))
                    stream.width, stream.height = size[1] + size[1] % 2, size[0] + size[0] % 2
                    stream.pix_fmt = "yuv420p"
                    stream.options = {"crf": str(CRF), "profile": "high", "preset": "medium", "x264-params": "mbtree=0"}
                assert size is not None  # set with the stream, from the first frame
                padded = np.pad(frame, ((0, size[0] % 2), (0, size[1] % 2), (0, 0)), mode="edge")
                container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(padded), format="rgb24")))
                count += 1
            if stream is None:
                raise SchemaError(f"{path}: no frames to write")
            container.mux(stream.encode(None))  # flush the encoder
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return count


def read_web_video(path: str | Path) -> tuple[np.ndarray, str, float]:
    """(frames (T, H, W, 3) uint8 RGB, codec name, frames per second) of a video, for checks."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(stream)])
        rate = stream.average_rate
        if rate is None:
            raise SchemaError(f"{path}: the video stream states no frame rate")
        return frames, stream.codec_context.name, float(rate)
