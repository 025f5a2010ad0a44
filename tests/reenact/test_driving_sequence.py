"""``reenact.sequence`` that the fit does not have lists the ones it has (issue 36, item 7)."""

from __future__ import annotations

from pathlib import Path

import pytest

from data_schemas.tables import SchemaError
from stages.reenact import _check_fitted


def test_a_missing_sequence_lists_the_fitted_ones(tmp_path: Path) -> None:
    for sequence in ("train", "test"):
        (tmp_path / sequence).mkdir()
        (tmp_path / sequence / "params.parquet").write_bytes(b"")
    _check_fitted(tmp_path, "test", "this subject")  # present: nothing to say
    with pytest.raises(
        SchemaError,
        match=r"reenact.sequence=nosuch: this subject has no fitted sequence 'nosuch' "
        r".*choose one of \['test', 'train'\]",
    ):
        _check_fitted(tmp_path, "nosuch", "this subject")


def _capture(root: Path, sequences: tuple[str, ...]) -> Path:
    from data_schemas.capture import CaptureIndex, SequenceInfo

    info = SequenceInfo(num_frames=4, frame_rate=10.0, width=32, height=32, has_masks=True, has_ground_truth=False)
    CaptureIndex(subject="mine", dataset="folder", sequences={s: info for s in sequences}).write(root)
    return root


def test_a_capture_without_the_held_out_motion_reenacts_its_training_motion(tmp_path: Path) -> None:
    """Issue 36 item 1: a folder capture with only train/ (test/ is optional) ran the whole DAG and then failed
    at reenact (`fit/test/params.parquet: missing params table`), and no report was written."""
    from stages.reenact import self_sequence

    train_only = _capture(tmp_path / "a", ("train",))
    sequence, note = self_sequence(train_only, "test")
    assert sequence == "train" and "no held-out 'test' sequence" in note and "training motion" in note
    both = _capture(tmp_path / "b", ("train", "test"))
    assert self_sequence(both, "test") == ("test", "")
    assert self_sequence(train_only, "nosuch") == ("nosuch", "")  # a sequence asked for by name stays an error
