"""Config sections typed by the core's own config dataclasses, so that a setting's name and type are defined once.

The training loops of ``avatar`` take frozen dataclasses (``StaticConfig``, ``DynamicTrainConfig``,
``SplattingConfig``) whose fields are the hyperparameters. A config section that feeds one declares its schema
with :func:`section_schema` (the core's fields with their types, less those the section does not hold, plus the
section's own settings) and builds the core's config with :func:`core_config` (every field from the section or
given), never field by field. ``tests/test_config_schemas.py`` checks that each such section's YAML sets every
field and that its values are the core's defaults, except where the pipeline chooses otherwise for a stated
reason.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from omegaconf import ListConfig

T = TypeVar("T")


def core_fields(core: type, exclude: Iterable[str] = ()) -> list[tuple[str, Any]]:
    """(name, resolved type) of the fields of the dataclass ``core``, less ``exclude``."""
    hints = typing.get_type_hints(core)
    skipped = set(exclude)
    unknown = skipped - {f.name for f in dataclasses.fields(core)}
    if unknown:
        raise ValueError(f"{core.__name__} has no field(s) {sorted(unknown)} to exclude")
    return [(f.name, hints[f.name]) for f in dataclasses.fields(core) if f.name not in skipped]


def section_schema(name: str, core: type, *, exclude: Iterable[str] = (), own: type | None = None) -> type:
    """A section's type schema named ``name``: the fields of the core's dataclass ``core`` less ``exclude`` (types
    only: the values live in the section's YAML), and those of the dataclass ``own`` (the section's own
    settings; its ``validate`` classmethod, if any, checks the section's ranges)."""
    derived = core_fields(core, exclude)
    if own is not None:
        clash = {n for n, _ in derived} & {f.name for f in dataclasses.fields(own)}
        if clash:
            raise ValueError(f"{own.__name__} redefines {sorted(clash)} of {core.__name__}: define each setting once")
    schema = dataclasses.make_dataclass(name, derived, bases=(own,) if own is not None else ())
    schema.__doc__ = (
        f"Types of a section feeding {core.__module__}.{core.__name__} (its fields less "
        f"{', '.join(exclude) or 'none'})" + (f" and {own.__name__}'s own settings." if own else ".")
    )
    return schema


def core_config(core: type[T], section: Mapping[str, Any], **given: Any) -> T:
    """The core's config ``core`` with every field not ``given`` read from ``section`` (a config section typed by
    :func:`section_schema`; a field missing there is a ``KeyError`` naming it)."""
    values = dict(given)
    for name, kind in core_fields(core, given):
        if name not in section:
            raise KeyError(f"{name}: a field of {core.__name__} that the config section does not set")
        value = section[name]
        if isinstance(value, ListConfig):  # a YAML list: the plain list, or the tuple the field is
            items = list(value)
            value = tuple(items) if typing.get_origin(kind) is tuple else items
        values[name] = value
    return core(**values)
