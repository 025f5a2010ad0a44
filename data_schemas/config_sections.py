"""Config sections typed by the core's own config dataclasses, so that a setting's name and type are defined once.

The training loops of ``avatar`` take frozen dataclasses (``WarmupTrainConfig``, ``DynamicTrainConfig``,
``SplattingConfig``) whose fields are the hyperparameters. A config section that feeds one declares its schema
with :func:`section_schema` (the core's fields with their types, less those the section does not hold, plus the
section's own settings) and builds the core's config with :func:`core_config` (every field from the section or
given), never field by field. ``tests/test_config_schemas.py`` checks that each such section's YAML sets every
field and that its values are the core's defaults, except where the pipeline chooses otherwise for a stated
reason.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from data_schemas.key_names import did_you_mean, key_paths

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


def field_docs(core: type) -> dict[str, str]:
    """field -> its documentation in the dataclass ``core``'s source: the full-line comments right above the
    field, then the comment at the end of its line ("" where it has neither)."""
    source = textwrap.dedent(inspect.getsource(core))
    lines = source.splitlines()
    trailing: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT and lines[token.start[0] - 1].strip() != token.string.strip():
            trailing[token.start[0]] = token.string.lstrip("#").strip()
    body = ast.parse(source).body[0]
    assert isinstance(body, ast.ClassDef)
    docs: dict[str, str] = {}
    for node in body.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            above: list[str] = []
            row = node.lineno - 2
            while row >= 0 and lines[row].strip().startswith("#"):
                above.insert(0, lines[row].strip().lstrip("#").strip())
                row -= 1
            docs[node.target.id] = " ".join([*above, trailing.get(node.lineno, "")]).strip()
    return docs


def yaml_value(value: Any) -> str:
    """``value`` (a bool, number, string or tuple/list of them) as a YAML flow value that reads back equal."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, float):
        text = repr(value)
        mantissa, e, exponent = text.partition("e")
        return f"{mantissa if '.' in mantissa else mantissa + '.0'}e{exponent}" if e else text
    return str(value)


def yaml_defaults(core: type, exclude: Iterable[str] = (), indent: str = "", width: int = 120) -> list[str]:
    """The YAML lines of the defaults of ``core``'s fields less ``exclude``, each documented by its comment in the
    dataclass (at the end of the line, or above the key where the line would pass ``width``). ``ValueError`` for a
    field without a default or without documentation."""
    docs = field_docs(core)
    defaults = {f.name: f.default for f in dataclasses.fields(core)}
    lines: list[str] = []
    for name, _ in core_fields(core, exclude):
        if defaults[name] is dataclasses.MISSING:
            raise ValueError(f"{core.__name__}.{name} has no default to write")
        if not docs[name]:
            raise ValueError(f"{core.__name__}.{name} has no comment: document it in the dataclass")
        line = f"{indent}{name}: {yaml_value(defaults[name])}"
        if len(line) + 3 + len(docs[name]) <= width:
            lines.append(f"{line}  # {docs[name]}")
        else:
            prefix = f"{indent}# "
            lines += [prefix + text for text in textwrap.wrap(docs[name], width - len(prefix), break_on_hyphens=False)]
            lines.append(line)
    return lines


def generated_block_markers(core: type) -> tuple[str, str]:
    """The comment lines that open and close the YAML block generated from ``core``."""
    name = f"{core.__module__}.{core.__qualname__}"
    return (
        f"# >>> generated from {name} (python -m avatar.config_defaults): edit the dataclass, not this block",
        f"# <<< generated from {name}",
    )


def with_generated_block(text: str, core: type, exclude: Iterable[str] = (), where: str = "") -> str:
    """``text`` (a YAML file) with its block generated from ``core`` rewritten (``where``: the file, for the error
    when its markers are missing); the block's indentation is its opening marker's."""
    opening, closing = generated_block_markers(core)
    lines = text.splitlines()
    starts = [i for i, line in enumerate(lines) if line.strip() == opening]
    ends = [i for i, line in enumerate(lines) if line.strip() == closing]
    if len(starts) != 1 or len(ends) != 1 or ends[0] < starts[0]:
        raise ValueError(f"{where}: needs exactly one block between '{opening}' and '{closing}'")
    indent = lines[starts[0]][: len(lines[starts[0]]) - len(lines[starts[0]].lstrip())]
    block = yaml_defaults(core, exclude, indent)
    return "\n".join([*lines[: starts[0] + 1], *block, *lines[ends[0] :]]) + "\n"


def check_section(section: Any, schema: type, where: str, errors: list[str]) -> DictConfig | None:
    """``section`` merged onto the structured ``schema`` (defaults filled, types converted).

    Unknown keys, wrong types and fields left without a value are appended to
    ``errors`` and give ``None``. Real stages keep their values in
    ``conf/stage/<name>.yaml`` and declare only types (no defaults) in the schema.
    """
    try:
        if OmegaConf.is_config(section):  # interpolations (stage.*.seed: ${seed}) resolve in the whole config first
            section = OmegaConf.to_container(section, resolve=True)
        merged = OmegaConf.merge(OmegaConf.structured(schema), section)
    except OmegaConfBaseException as exc:
        msg = str(exc).splitlines()[0]
        key = getattr(exc, "full_key", None)
        if isinstance(exc, ConfigKeyError) and key:  # a key the schema does not have: the one meant, where one is close
            paths = key_paths(OmegaConf.structured(schema)) + key_paths(section)  # the schema's blocks, as given
            meant = did_you_mean(f"{where}.{key}", (f"{where}.{path}" for path in paths))
            msg = f"not a setting of {where}{meant}"
        errors.append(f"{where}.{key}: {msg}" if key else f"{where}: {msg}")
        return None
    missing = sorted(OmegaConf.missing_keys(merged))
    if missing:
        errors.append(f"{where}: missing value for {', '.join(missing)}")
        return None
    assert isinstance(merged, DictConfig)  # merged onto a structured dataclass
    validate = getattr(schema, "validate", None)
    problems = validate(merged) if callable(validate) else []
    errors.extend(f"{where}.{problem}" for problem in problems)
    return None if problems else merged


def schema_problems(section: Any, schema: type, where: str) -> list[str]:
    """The problems :func:`check_section` finds in ``section`` (at ``where``) against ``schema``, one line each
    (a missing section is one)."""
    if section is None:
        return [f"{where}: missing (expected the fields of {schema.__name__})"]
    errors: list[str] = []
    check_section(section, schema, where, errors)
    return errors
