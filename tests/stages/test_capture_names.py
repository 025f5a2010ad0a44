"""Names that become paths (camera ids, sequence folders, subjects) are checked once, where they enter, and a
name that could leave its folder, hide, or share a path with another artifact is refused before any stage runs,
with one line naming the file and the fix."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from data_schemas.cameras import CAMERAS, read_cameras, write_cameras
from data_schemas.capture import CAPTURE_INDEX, CaptureIndex, SequenceInfo, video_path
from data_schemas.names import camera_id_problem, folder_name_problem
from data_schemas.tables import SchemaError, write_table
from data_schemas.video import write_video
from pipeline.cli import run_app
from pipeline.config import ConfigError
from tests.conftest import compose_cfg
from tests.stages.test_folder_capture import _camera, _cfg, _frames, make_capture

HOSTILE = "<img src=x onerror=alert(2)>"
UNSAFE_CAMERA_IDS = [
    "",
    ".",
    "..",
    ".hidden",
    "a/b",
    "a\\b",
    "/etc",
    "a b",
    "cam#1",
    "cam?1",
    HOSTILE,
    "x" * 65,
    "orbit",
    "Orbit",
    "cam00_gt",
    "cam00_vs_gt",
    "con",
    "NUL.1",
    "lpt9",
    "cam\x00",
    "câm",
]
SAFE_CAMERA_IDS = ["cam00", "400262", "22.1", "cam-1_a", "C0001", "x" * 64, "gt", "orbits", "console"]


@pytest.mark.parametrize("camera_id", UNSAFE_CAMERA_IDS)
def test_an_unsafe_camera_id_is_refused(camera_id: str) -> None:
    assert camera_id_problem(camera_id) is not None


@pytest.mark.parametrize("camera_id", SAFE_CAMERA_IDS)
def test_a_safe_camera_id_is_accepted(camera_id: str) -> None:
    assert camera_id_problem(camera_id) is None


@pytest.mark.parametrize("name", ["", ".", "..", "a.b", "a/b", "_x", "-x", HOSTILE, "aux", "y" * 65, None, 3])
def test_an_unsafe_folder_name_is_refused(name: object) -> None:
    assert folder_name_problem(name) is not None


@pytest.mark.parametrize("name", ["train", "test", "cross_synth_b", "take-2", "S1"])
def test_a_safe_folder_name_is_accepted(name: str) -> None:
    assert folder_name_problem(name) is None


def _with_camera(root: Path, camera_id: str) -> Path:
    """A folder capture whose third camera is named ``camera_id`` (calibration and video)."""
    subject = root / "alice"
    cams = [_camera(0), _camera(1), replace(_camera(2), camera_id=camera_id)]
    write_table(
        subject / "cameras.parquet",
        CAMERAS,
        {
            "camera_id": [c.camera_id for c in cams],
            "width": np.array([c.width for c in cams]),
            "height": np.array([c.height for c in cams]),
            "K": np.stack([c.K.reshape(9) for c in cams]),
            "world_to_cam": np.stack([c.world_to_cam.reshape(16) for c in cams]),
            "dist": np.stack([c.dist for c in cams]),
            "split": [c.split for c in cams],
        },
    )
    for i, cam in enumerate(cams):
        write_video(subject / "train" / "videos" / f"{cam.camera_id}.mp4", _frames(i), 25.0)
    return subject


def _run(tmp_path: Path, *extra: str) -> None:
    run_app(_cfg(tmp_path, *extra))


def _written(tmp_path: Path) -> list[Path]:
    """Every stage artifact written under the outputs folder (nothing counts that is not a stage's)."""
    out = tmp_path / "out" / "alice"
    return sorted(p for p in out.glob("*/_manifest.json")) if out.is_dir() else []


@pytest.mark.parametrize("camera_id", ["..", "orbit", "cam02_gt"])
def test_a_folder_capture_with_an_unsafe_camera_id_is_refused_before_any_stage(tmp_path, camera_id: str) -> None:
    """A camera named '..' (video '...mp4') used to write its crops into frames/<sequence>/ of another camera and
    certify them as cached; one named 'orbit' lost its reenactment to the orbit view."""
    _with_camera(tmp_path / "data", camera_id)
    for extra in ([], ["run.dry=true"]):
        with pytest.raises(ConfigError) as caught:
            _run(tmp_path, *extra)
        message = str(caught.value)
        assert f"camera id {camera_id!r}" in message
        assert f"{camera_id}.mp4" in message  # the file to rename
        assert _written(tmp_path) == []


def test_a_folder_capture_with_a_hostile_sequence_folder_is_refused(tmp_path) -> None:
    subject = make_capture(tmp_path / "data")
    os.rename(subject / "train", subject / HOSTILE)
    with pytest.raises(ConfigError, match=r"sequence folder .*: use letters, digits") as caught:
        _run(tmp_path)
    assert "rename the folder" in str(caught.value)
    assert _written(tmp_path) == []


def test_the_adapter_itself_refuses_unsafe_names_before_writing(tmp_path) -> None:
    """The capture stage refuses too (a config check can be bypassed by a caller of the adapter)."""
    from omegaconf import OmegaConf

    from importers.folder import import_folder

    _with_camera(tmp_path / "data", "..")
    out = tmp_path / "capture"
    out.mkdir()
    dataset = OmegaConf.create({"root": str(tmp_path / "data"), "calibration": "auto"})
    with pytest.raises(SchemaError, match=r"camera id '\.\.'"):
        import_folder(dataset, "alice", out, 25.0)
    assert list(out.iterdir()) == []


def test_cameras_table_with_an_unsafe_id_is_refused_on_write_and_on_read(tmp_path) -> None:
    cams = [_camera(0), replace(_camera(1), camera_id="..")]
    with pytest.raises(SchemaError, match=r"camera id '\.\.': use letters"):
        write_cameras(tmp_path / "w" / "cameras.parquet", cams)
    subject = _with_camera(tmp_path, "../x")  # a table written by another tool
    with pytest.raises(SchemaError, match=r"cameras\.parquet: camera id '\.\./x'"):
        read_cameras(subject / "cameras.parquet")


def test_capture_index_with_an_unsafe_sequence_is_refused_on_write_and_on_read(tmp_path) -> None:
    info = SequenceInfo(3, 25.0, 48, 48, False, False)
    with pytest.raises(SchemaError, match=r"sequence '\.\.'"):
        CaptureIndex("alice", "folder", {"..": info}).write(tmp_path)
    CaptureIndex("alice", "folder", {"train": info}).write(tmp_path)
    body = json.loads((tmp_path / CAPTURE_INDEX).read_text())
    body["sequences"]["../../x"] = body["sequences"].pop("train")
    (tmp_path / CAPTURE_INDEX).write_text(json.dumps(body))
    with pytest.raises(SchemaError, match=r"capture\.json: sequence '\.\./\.\./x'"):
        CaptureIndex.read(tmp_path)


@pytest.mark.parametrize("subject", ["con", "..", "a.b"])
def test_an_unsafe_subject_is_refused(tmp_path, subject: str) -> None:
    with pytest.raises(ConfigError, match=rf"subject={subject!r}"):
        run_app(compose_cfg([f"subject={subject}", f"paths.outputs={tmp_path}", "run.dry=true"]))


def test_a_good_folder_capture_still_imports(tmp_path) -> None:
    make_capture(tmp_path / "data")
    assert video_path(tmp_path / "data" / "alice", "train", "cam00").is_file()
    _run(tmp_path, "run.until=capture")
    assert len(_written(tmp_path)) == 1
