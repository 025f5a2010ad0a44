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
    with pytest.raises(SchemaError, match=r"reenact.sequence=nosuch: this subject has no fitted sequence 'nosuch' "
                                          r".*choose one of \['test', 'train'\]"):
        _check_fitted(tmp_path, "nosuch", "this subject")
