"""``dataset.*`` frame selection and training cameras are refused before any stage runs (issue 36, item 6)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from tests.conftest import compose_cfg

BAD = [
    (["dataset.train_cameras=[]"], "dataset.train_cameras=[]: a non-empty list of camera ids"),
    (["dataset.train_cameras=[cam99]"], "dataset.train_cameras=['cam99']: choose some but not all"),
    (["dataset.train_cameras=[cam00,cam01,cam02,cam03,cam04,cam05,cam06,cam07]"], "choose some but not all"),
    (
        ["dataset=folder", "dataset.root=/nowhere", "dataset.start_frame=abc"],
        "dataset.start_frame='abc': must be a whole",
    ),
    (["dataset=folder", "dataset.root=/nowhere", "dataset.frame_step=2.5"], "dataset.frame_step=2.5: must be a whole"),
    (["dataset=folder", "dataset.root=/nowhere", "dataset.frame_step=0"], "dataset.frame_step=0: must be >= 1"),
    (["dataset=folder", "dataset.root=/nowhere", "dataset.max_frames=0"], "dataset.max_frames=0: must be >= 1"),
]


@pytest.mark.parametrize(("overrides", "message"), BAD)
def test_bad_dataset_values_fail_in_the_dry_run_naming_the_key(
    tmp_path: Path, overrides: list[str], message: str
) -> None:
    cfg = compose_cfg([f"paths.outputs={tmp_path / 'out'}", "run.progress=false", "run.dry=true", *overrides])
    with pytest.raises(ConfigError) as info:
        run_app(cfg)
    assert sum(message in line for line in str(info.value).splitlines()) == 1, str(info.value)
    assert not (tmp_path / "out").exists()


def test_good_dataset_values_pass(tmp_path: Path) -> None:
    (tmp_path / "data" / "synth_a").mkdir(parents=True)  # a dry run checks that the capture folder is there
    for overrides in (
        ["dataset.train_cameras=[cam04]"],
        ["dataset=folder", f"dataset.root={tmp_path / 'data'}", "dataset.max_frames=5", "dataset.frame_step=2"],
    ):
        run_app(compose_cfg([f"paths.outputs={tmp_path / 'out'}", "run.progress=false", "run.dry=true", *overrides]))


@pytest.mark.parametrize(
    ("driver", "message"),
    [
        ("synth_a", "names this run's own subject 'synth_a'"),
        ("/nonexistent/file.parquet", "reenact.driver=/nonexistent/file.parquet: no such file"),
    ],
)
def test_a_bad_reenactment_driver_is_one_config_error_in_the_dry_run(tmp_path: Path, driver: str, message: str) -> None:
    """Issue 36, item 7: the subject itself as its own driver (use reenact.driver=self) and a missing parameter
    file are config errors (one line, no traceback from the command line), found before any work."""
    cfg = compose_cfg(
        [
            f"paths.outputs={tmp_path / 'out'}",
            "run.progress=false",
            "run.dry=true",
            "subject=synth_a",
            f"reenact.driver={driver}",
        ]
    )
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        run_app(cfg)
    assert not (tmp_path / "out" / "synth_a" / "capture").exists()


def test_each_dataset_defaults_to_the_detectors_its_captures_need(tmp_path: Path) -> None:
    """The synthetic capture's own keypoints and masks; MediaPipe for a folder of footage; DECAF's shipped keypoints
    where the release has them for the subject, else MediaPipe. A command-line value still wins."""

    def detectors(*overrides: str) -> tuple[str, str]:
        cfg = compose_cfg(list(overrides))
        return str(cfg.stage.frames.segmenter), str(cfg.stage.keypoints.detector)

    assert detectors() == ("key", "ground_truth")
    assert detectors("dataset=folder", "dataset.root=/data") == ("mediapipe", "mediapipe")
    assert detectors("dataset=folder", "dataset.root=/data", "stage.frames.segmenter=key") == ("key", "mediapipe")
    (tmp_path / "test" / "right_hand_keys" / "S1").mkdir(parents=True)
    decaf = ("dataset=decaf", f"dataset.root={tmp_path}")
    assert detectors(*decaf, "subject=S1")[1] == "provided"
    assert detectors(*decaf, "subject=S2")[1] == "mediapipe"
    assert detectors(*decaf, "subject=S1", "stage.keypoints.detector=mediapipe")[1] == "mediapipe"
