"""tests/smoke_digests.py, the tool that shows a refactor left every output alone: its comparison names every
difference, and a Parquet table is compared without its wall-time column."""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq

from tests.smoke_digests import compare, content_digest


def test_compare_names_every_difference_and_nothing_else() -> None:
    before = {"files": {"a": "1", "b": "2", "gone": "3"}, "keys": {"s": "k"}, "timed": {}}
    after = {"files": {"a": "1", "b": "X", "new": "4"}, "keys": {"s": "k2"}, "timed": {}}
    assert compare(before, after) == [
        "files: only before: gone",
        "files: only after: new",
        "files: changed: b",
        "keys: changed: s",
    ]
    assert compare(before, before) == []


def test_a_table_is_compared_without_its_wall_times(tmp_path) -> None:
    paths = []
    for i, wall in enumerate((1.5, 9.0)):
        paths.append(tmp_path / f"comparison{i}.parquet")
        pq.write_table(pa.table({"psnr": [30.0, 31.0], "train_wall_s": [wall, wall]}), paths[-1])
    assert content_digest(paths[0], "bytes0") == content_digest(paths[1], "bytes1")
    other = tmp_path / "other.parquet"
    pq.write_table(pa.table({"psnr": [30.0, 31.5], "train_wall_s": [1.5, 1.5]}), other)
    assert content_digest(other, "bytes2") != content_digest(paths[0], "bytes0")
    plain = tmp_path / "plain.parquet"
    pq.write_table(pa.table({"psnr": [30.0]}), plain)
    assert content_digest(plain, "its sha256") == "its sha256"  # no wall time: the manifest's digest of its bytes
