"""Writers on a full disk: an error that names the file and says "no space left on device", and no file
left behind (OpenCV's writers used to report success, leaving an undecodable video or a truncated PNG).

The real test mounts a small tmpfs (root only; skipped elsewhere); the simulated ones run everywhere.
"""

from __future__ import annotations

import errno
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

import data_schemas.video
import data_schemas.writes
from data_schemas.gaussians_ply import GaussianCloud, write_gaussians_ply
from data_schemas.images import write_exr, write_png
from data_schemas.keypoints import KEYPOINTS
from data_schemas.tables import write_table
from data_schemas.video import read_video, write_video
from data_schemas.writes import WriteError
from tests.conftest import small_disk

RNG = np.random.default_rng(0)
DISK_KIB, FREE_KIB = 64, 8


@pytest.fixture
def full_disk(tmp_path: Path) -> Iterator[Path]:
    """A 64 KiB tmpfs holding a filler that leaves 8 KiB free."""
    with small_disk(tmp_path / "disk", DISK_KIB) as mount:
        (mount / "filler").write_bytes(b"\xff" * ((DISK_KIB - FREE_KIB) * 1024))
        yield mount


def _noise(*shape: int) -> np.ndarray:
    return RNG.integers(0, 256, shape, dtype=np.uint8)


def _keypoint_rows(n: int) -> dict:
    return {
        "frame": np.arange(n),
        "camera_id": ["cam00"] * n,
        "part": ["face"] * n,
        "uvc": [RNG.random(3 * 70).astype(np.float32) for _ in range(n)],
    }


def _cloud(n: int) -> GaussianCloud:
    return GaussianCloud(
        means=RNG.normal(size=(n, 3)),
        sh_dc=RNG.normal(size=(n, 3)),
        sh_rest=np.zeros((n, 0, 3)),
        opacity_logits=RNG.normal(size=n),
        log_scales=RNG.normal(size=(n, 3)),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
    )


WRITERS: dict[str, tuple[str, Callable[[Path], object]]] = {
    "video": ("v.mp4", lambda p: write_video(p, _noise(12, 96, 96, 3), 25.0)),
    "png": ("a.png", lambda p: write_png(p, _noise(96, 96, 3))),
    "parquet": ("k.parquet", lambda p: write_table(p, KEYPOINTS, _keypoint_rows(200))),
    "exr": ("a.exr", lambda p: write_exr(p, {"RGB": RNG.random((64, 64, 3), dtype=np.float32)})),
    "ply": ("g.ply", lambda p: write_gaussians_ply(p, _cloud(2000))),
}


@pytest.mark.parametrize("kind", list(WRITERS))
def test_writer_on_a_full_disk_names_the_file_and_the_cause(full_disk: Path, kind: str):
    name, write = WRITERS[kind]
    with pytest.raises(OSError) as info:
        write(full_disk / name)
    message = str(info.value)
    assert message.startswith(f"{full_disk / name}: could not write"), message
    assert "no space left on device" in message.lower(), message
    assert not (full_disk / name).exists(), "a partial file was left behind"


@pytest.mark.parametrize("kind", list(WRITERS))
def test_writer_with_room_reads_back_what_it_wrote(tmp_path: Path, kind: str):
    name, write = WRITERS[kind]
    write(tmp_path / name)
    assert (tmp_path / name).stat().st_size > 0


# ---------------------------------------------------------------------------- simulated (no root needed)
class _IndexLosingWriter:
    """cv2.VideoWriter that, like OpenCV on a full disk, reports success but never writes the index."""

    real = cv2.VideoWriter

    def __init__(self, path: str, *args: object) -> None:
        self._inner, self._path = self.real(path, *args), Path(path)

    def isOpened(self) -> bool:  # OpenCV's name
        return self._inner.isOpened()

    def write(self, frame: np.ndarray) -> None:
        self._inner.write(frame)

    def release(self) -> None:
        self._inner.release()
        data = self._path.read_bytes()
        self._path.write_bytes(data[: data.find(b"moov") - 4])


def test_video_writer_that_loses_the_index_is_not_a_success(tmp_path, monkeypatch):
    monkeypatch.setattr(data_schemas.video.cv2, "VideoWriter", _IndexLosingWriter)
    path = tmp_path / "v.mp4"
    with pytest.raises(WriteError, match=r"v\.mp4: could not write the video \(3 frames encoded, 0 in the file"):
        write_video(path, _noise(3, 32, 32, 3), 25.0)
    assert not path.exists()


def test_video_written_normally_reads_back(tmp_path):
    frames = _noise(3, 32, 32, 3)
    write_video(tmp_path / "v.mp4", frames, 25.0)
    assert read_video(tmp_path / "v.mp4").shape == frames.shape


def test_enospc_from_the_os_names_the_file(tmp_path, monkeypatch):
    def no_space(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(data_schemas.writes, "open", no_space, raising=False)
    with pytest.raises(WriteError, match=r"a\.png: could not write the PNG: No space left on device") as info:
        write_png(tmp_path / "a.png", _noise(8, 8, 3))
    assert info.value.errno == errno.ENOSPC
    monkeypatch.setattr(pq, "write_table", no_space)
    with pytest.raises(WriteError, match=r"k\.parquet: could not write the keypoints table: No space left"):
        write_table(tmp_path / "k.parquet", KEYPOINTS, _keypoint_rows(2))
