"""A stage reading another subject's artifacts: the driver's digests enter its key."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.cli import run_app
from pipeline.config import ConfigError
from pipeline.runner import MissingUpstream
from tests.conftest import compose_cfg


@pytest.fixture
def subject_cfg(tmp_path: Path):
    def make(subject: str, driver: str = "self", value: int = 1, *extra: str):
        return compose_cfg(
            [
                "pipeline.stages_module=tests.toy_subjects",
                "stage=[]",
                f"+stage.a.value={value}",
                f"+stage.drive.driver={driver}",
                f"subject={subject}",
                f"paths.outputs={tmp_path / 'out'}",
                "run.progress=false",
                *extra,
            ]
        )

    return make


def actions(reports) -> dict[str, str]:
    return {r.stage: r.action for r in reports}


def test_driver_subject_is_an_input_and_its_change_reruns_the_reader(subject_cfg, tmp_path):
    run_app(subject_cfg("s2", value=5))
    first = run_app(subject_cfg("s1", "s2"))
    assert actions(first) == {"a": "run", "drive": "run"}
    assert (tmp_path / "out" / "s1" / "drive" / "drive.txt").read_text() == "s1: a=1\ns2: a=5\n"
    assert actions(run_app(subject_cfg("s1", "s2"))) == {"a": "cached", "drive": "cached"}
    run_app(subject_cfg("s2", value=6))  # the driver is re-fitted
    again = run_app(subject_cfg("s1", "s2"))
    assert actions(again) == {"a": "cached", "drive": "run"}
    assert {r.stage: r.reason for r in again}["drive"] == "upstream changed: s2:a"
    assert (tmp_path / "out" / "s1" / "drive" / "drive.txt").read_text() == "s1: a=1\ns2: a=6\n"


def test_self_driven_reads_no_other_subject(subject_cfg, tmp_path):
    assert actions(run_app(subject_cfg("s1"))) == {"a": "run", "drive": "run"}
    assert (tmp_path / "out" / "s1" / "drive" / "drive.txt").read_text() == "s1: a=1\nself\n"


def test_a_driver_without_artifacts_or_with_a_bad_name_is_one_clear_error(subject_cfg, tmp_path):
    with pytest.raises(MissingUpstream, match="subject=s3 run.until=a"):
        run_app(subject_cfg("s1", "s3"))
    assert not (tmp_path / "out" / "s1" / "drive").exists()
    with pytest.raises(ConfigError, match="subject='../x'"):
        run_app(subject_cfg("s1", "'../x'"))
