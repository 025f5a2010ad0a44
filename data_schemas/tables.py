"""Typed Parquet tables: one explicit pyarrow schema per artifact, validated on write and read.

Every table carries in its schema metadata the artifact name, ``schema_version``
and the unit of each column. Vectors are fixed-size lists (``vec_f32`` /
``vec_f64``), read back as ``(N, size)`` numpy arrays. Files are zstd-compressed.
Every validation error names the file, the column and what was expected.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from numpy.typing import ArrayLike

from data_schemas.writes import write_failed

Kind = Literal["int32", "int64", "float32", "float64", "bool", "string", "vec_f32", "vec_f64", "list_f32"]

_SCALAR_TYPES: dict[str, pa.DataType] = {
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
    "bool": pa.bool_(),
    "string": pa.string(),
}
_VECTOR_DTYPES: dict[str, tuple[pa.DataType, type[np.floating]]] = {
    "vec_f32": (pa.float32(), np.float32),
    "vec_f64": (pa.float64(), np.float64),
    "list_f32": (pa.float32(), np.float32),
}


class SchemaError(ValueError):
    """An artifact does not match its schema; the message names file, column and expectation."""


@dataclass(frozen=True)
class Column:
    """One column of a table.

    Attributes:
        name: column name.
        kind: storage kind; ``vec_*`` are fixed-size lists, ``list_f32`` variable-length.
        size: fixed length of a ``vec_*`` column; ``None`` lets the writer choose it
            (uniform within one file, e.g. the number of shape coefficients).
        unit: physical unit recorded in the metadata ("m", "rad", "px", "" for none).
        finite: reject NaN/Inf in float data.
        doc: one line of documentation.
    """

    name: str
    kind: Kind
    size: int | None = None
    unit: str = ""
    finite: bool = True
    doc: str = ""

    def arrow_type(self, size: int | None) -> pa.DataType:
        if self.kind in _SCALAR_TYPES:
            return _SCALAR_TYPES[self.kind]
        value_type = _VECTOR_DTYPES[self.kind][0]
        if self.kind == "list_f32":
            return pa.list_(value_type)
        assert size is not None
        return pa.list_(value_type, size)


@dataclass(frozen=True)
class TableSchema:
    """An artifact's table layout and version."""

    name: str
    version: int
    columns: tuple[Column, ...]
    doc: str = ""

    @property
    def column_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    def column(self, name: str) -> Column:
        return next(c for c in self.columns if c.name == name)

    def metadata(self) -> dict[bytes, bytes]:
        return {
            b"artifact": self.name.encode(),
            b"schema_version": str(self.version).encode(),
            b"units": json.dumps({c.name: c.unit for c in self.columns if c.unit}).encode(),
        }


def _to_arrow(path: Path, col: Column, values: Any, n_rows: int) -> pa.Array:
    where = f"{path}: column '{col.name}'"
    if col.kind == "string":
        values = [str(v) for v in values]
        if len(values) != n_rows:
            raise SchemaError(f"{where}: expected {n_rows} rows, got {len(values)}")
        return pa.array(values, type=pa.string())
    if col.kind == "list_f32":
        rows = [np.asarray(v, dtype=np.float32).ravel() for v in values]
        if len(rows) != n_rows:
            raise SchemaError(f"{where}: expected {n_rows} rows, got {len(rows)}")
        if col.finite and any(not np.isfinite(r).all() for r in rows):
            raise SchemaError(f"{where}: contains NaN or Inf {_in_rows([not np.isfinite(r).all() for r in rows])}")
        return pa.array([r.tolist() for r in rows], type=pa.list_(pa.float32()))
    arr = np.asarray(values)
    if arr.shape[:1] != (n_rows,):
        raise SchemaError(f"{where}: expected {n_rows} rows, got array of shape {arr.shape}")
    if col.kind in _SCALAR_TYPES:
        if arr.ndim != 1:
            raise SchemaError(f"{where}: expected a 1-D array of {col.kind}, got shape {arr.shape}")
        arr = arr.astype(np.dtype(col.kind if col.kind != "bool" else np.bool_))
        if col.finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise SchemaError(f"{where}: contains NaN or Inf {_in_rows(~np.isfinite(arr))}")
        return pa.array(arr, type=_SCALAR_TYPES[col.kind])
    value_type, dtype = _VECTOR_DTYPES[col.kind]
    flat = arr.reshape(n_rows, -1).astype(dtype)
    size = flat.shape[1]
    if col.size is not None and size != col.size:
        raise SchemaError(f"{where}: expected vectors of length {col.size}, got {size}")
    if col.finite and not np.isfinite(flat).all():
        raise SchemaError(f"{where}: contains NaN or Inf {_in_rows(~np.isfinite(flat).all(1))}")
    return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(flat).ravel(), type=value_type), size)


def write_table(path: str | Path, schema: TableSchema, data: Mapping[str, Any]) -> None:
    """Validate ``data`` (column name -> values, vectors as ``(N, size)``) and write it as Parquet."""
    path = Path(path)
    names = [c.name for c in schema.columns]
    unknown = sorted(set(data) - set(names))
    missing = [n for n in names if n not in data]
    if unknown or missing:
        raise SchemaError(f"{path}: {schema.name} expects columns {names}; missing {missing}, unknown {unknown}")
    n_rows = len(data[names[0]])
    arrays = [_to_arrow(path, c, data[c.name], n_rows) for c in schema.columns]
    fields = [pa.field(c.name, a.type, nullable=False) for c, a in zip(schema.columns, arrays)]
    table = pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata=schema.metadata()))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path, compression="zstd")
        written = pq.read_metadata(path).num_rows  # the footer, read back: cheap
    except (OSError, pa.ArrowException) as exc:
        raise write_failed(path, f"{schema.name} table", exc) from exc
    if written != n_rows:
        raise write_failed(path, f"{schema.name} table", OSError(f"{written} of {n_rows} rows read back"))


def write_records(path: str | Path, schema: TableSchema, records: Sequence[Any]) -> None:
    """:func:`write_table` of one row per record, each column the record's attribute of that name (a training
    loop's log rows)."""
    write_table(path, schema, {name: np.array([getattr(r, name) for r in records]) for name in schema.column_names})


def read_table(path: str | Path, schema: TableSchema) -> dict[str, np.ndarray | list[Any]]:
    """Read and validate a table: scalars as 1-D arrays, ``vec_*`` as ``(N, size)``, strings and
    ``list_f32`` as lists."""
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: missing {schema.name} table")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path}: not a readable Parquet file ({exc})") from exc
    validate_table(path, table, schema)
    out: dict[str, np.ndarray | list[Any]] = {}
    for c in schema.columns:
        col = table.column(c.name).combine_chunks()
        if c.kind == "string" or c.kind == "list_f32":
            out[c.name] = col.to_pylist()
        elif c.kind in _SCALAR_TYPES:
            out[c.name] = col.to_numpy(zero_copy_only=False)
        else:
            size = col.type.list_size
            out[c.name] = col.flatten().to_numpy().reshape(len(col), size)
    return out


def validate_table(path: Path, table: pa.Table, schema: TableSchema) -> None:
    """Check artifact name, schema version, column set, types and finiteness."""
    meta = table.schema.metadata or {}
    artifact = meta.get(b"artifact", b"").decode()
    version = meta.get(b"schema_version", b"").decode()
    if artifact != schema.name:
        raise SchemaError(f"{path}: expected a '{schema.name}' table, found '{artifact or 'no artifact tag'}'")
    if version != str(schema.version):
        raise SchemaError(
            f"{path}: {schema.name} schema_version {version or '?'} != supported {schema.version}; "
            f"regenerate it with this version of the pipeline"
        )
    for c in schema.columns:
        if c.name not in table.column_names:
            raise SchemaError(f"{path}: missing column '{c.name}' ({c.kind})")
        actual = table.schema.field(c.name).type
        size = getattr(actual, "list_size", None)
        expected = c.arrow_type(size if c.size is None else c.size)
        if actual != expected:
            raise SchemaError(f"{path}: column '{c.name}' has type {actual}, expected {expected}")
        if c.finite and c.kind not in ("string", "bool", "int32", "int64"):
            rows = _nonfinite_rows(table.column(c.name).combine_chunks())
            if rows.size:
                raise SchemaError(f"{path}: column '{c.name}' contains NaN or Inf {_in_rows(rows, table)}")


def _nonfinite_rows(values: pa.Array) -> np.ndarray:
    """The indices of the rows of a float column (scalars, or fixed-size or variable-length lists of them) that hold
    a NaN or an infinity, ascending."""
    if pa.types.is_list(values.type) or pa.types.is_fixed_size_list(values.type):
        flat = pc.list_flatten(values).to_numpy(zero_copy_only=False)
        parents = pc.list_parent_indices(values).to_numpy(zero_copy_only=False)
    else:
        flat = values.to_numpy(zero_copy_only=False)
        parents = np.arange(len(flat))
    return np.unique(parents[~np.isfinite(flat)])


def _in_rows(bad: ArrayLike, table: pa.Table | None = None, shown: int = 5) -> str:
    """Where a column is not finite, for its message: ``in frames [1, 2]`` by the table's ``frame`` column where it
    has one (a per-frame table), else ``in rows [...]`` (from 0); the first ``shown``, and how many there are.
    ``bad``: a flag per row, or the rows' indices."""
    flags = np.asarray(bad)
    rows = np.flatnonzero(flags) if flags.dtype == bool else flags.astype(int)
    label = "rows"
    if table is not None and "frame" in table.column_names:
        rows, label = table.column("frame").to_numpy()[rows], "frames"
    more = f" ({rows.size} in all)" if rows.size > shown else ""
    return f"in {label} {rows[:shown].tolist()}{more}"
