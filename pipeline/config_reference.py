"""The config reference of the docs (``docs/reference/config-keys.md``), generated so it cannot drift.

Every key of the composed default config (``conf/``: the default dataset, every stage, the default preset and
method), with its default, its type where a schema declares one (the stages' ``config_schema`` dataclasses,
``RunConfig``, ``PathsConfig``, ``QualityConfig``), the file that sets the default, and the comment next to the
key (or the comment block just above it) in that file or in the first file that explains it.

``python -m pipeline.config_reference`` rewrites the page; ``tests/test_docs.py`` checks the committed page
against :func:`render`.
"""

from __future__ import annotations

import dataclasses
import json
import re
import typing
from collections.abc import Iterator
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.config import PathsConfig, QualityConfig, RunConfig
from pipeline.registry import load_registry

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
PAGE = Path(__file__).resolve().parent.parent / "docs" / "reference" / "config-keys.md"
#: the files of the default composition, in the order Hydra merges them (a later one overrides an earlier one)
DEFAULT_FILES = (
    "dataset/synthetic.yaml",
    "stage/*.yaml",
    "config.yaml",
    "quality/smoke.yaml",
    "method/interactavatar.yaml",
)
_KEY_LINE = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w\-]*):(?P<value>[^#]*?)(?:\s+#\s?(?P<comment>.*))?$")


def _package(path: Path) -> str:
    """Where ``path``'s keys go: its ``# @package`` line, else its config group (``dataset``), root for
    config.yaml."""
    for line in path.read_text().splitlines()[:3]:
        match = re.match(r"#\s*@package\s+(\S+)", line)
        if match:
            return "" if match.group(1) == "_global_" else match.group(1)
    group = path.parent.relative_to(CONF_DIR).as_posix()
    return "" if group == "." else group


def _commented_keys(path: Path) -> Iterator[tuple[str, str]]:
    """(dotted key, its comment) for every key of a YAML file: the comment on the key's line, else the block
    of full-line comments right above it."""
    stack: list[tuple[int, str]] = []
    above: list[str] = []
    prefix = _package(path)
    for number, line in enumerate(path.read_text().splitlines()):
        stripped = line.strip()
        if stripped.startswith(("# >>> generated", "# <<< generated")):  # avatar.config_defaults' block markers
            above = []
            continue
        if stripped.startswith("#"):
            header = number == len(above)  # the file's opening comment describes the file, not its first key
            above = [] if header and "@package" in stripped else above
            above.append("" if header else stripped.lstrip("#").strip())
            continue
        match = _KEY_LINE.match(line)
        if match is None:
            above = []
            continue
        indent = len(match.group("indent"))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, match.group("key")))
        key = ".".join(([prefix] if prefix else []) + [k for _, k in stack])
        comment = match.group("comment") or " ".join(c for c in above if c)
        above = []
        if comment:
            yield key, comment.strip()


def _files() -> list[Path]:
    return [p for pattern in DEFAULT_FILES for p in sorted(CONF_DIR.glob(pattern))]


def _leaves(node: DictConfig, prefix: str = "") -> Iterator[tuple[str, object]]:
    for key in node:
        value = node._get_node(key)
        dotted = prefix + str(key)
        if isinstance(value, DictConfig) and len(value) > 0:
            yield from _leaves(value, dotted + ".")
        else:
            yield dotted, value


def _schema_types() -> dict[str, str]:
    """Dotted key -> type, from the dataclasses that check the config."""
    roots: list[tuple[str, type]] = [("run", RunConfig), ("paths", PathsConfig), ("quality", QualityConfig)]
    roots += [(f"stage.{s.name}", s.config_schema) for s in load_registry("stages") if s.config_schema is not None]
    types: dict[str, str] = {}

    def walk(prefix: str, schema: type) -> None:
        hints = typing.get_type_hints(schema)
        for f in dataclasses.fields(schema):
            hint = hints[f.name]
            if isinstance(hint, type) and dataclasses.is_dataclass(hint):
                walk(f"{prefix}.{f.name}", hint)
            else:
                types[f"{prefix}.{f.name}"] = re.sub(
                    r"\b(typing|builtins)\.", "", hint.__name__ if isinstance(hint, type) else str(hint)
                )

    for prefix, schema in roots:
        walk(prefix, schema)
    return types


def _default(value: object) -> str:
    """A default as the command line writes it (interpolations unresolved)."""
    if isinstance(value, (DictConfig, ListConfig)):
        text = json.dumps(OmegaConf.to_container(value, resolve=False))
    else:
        text = str(value._value() if hasattr(value, "_value") else value)
    return text.replace("|", "\\|").replace("\n", " ")


def render(cfg: DictConfig, datasets: dict[str, DictConfig] | None = None) -> str:
    """The page for the composed default config ``cfg`` (no ``hydra`` node), then, for each other dataset of
    ``datasets`` (name -> the config composed with ``dataset=<name>``), the keys its file sets."""
    set_by: dict[str, str] = {}
    explained: dict[str, str] = {}
    for path in _files():
        rel = path.relative_to(CONF_DIR).as_posix()
        for key, comment in _commented_keys(path):
            explained[key] = comment  # a later file's comment on the same key is the more specific one
        loaded = OmegaConf.load(path)
        if not isinstance(loaded, DictConfig):
            raise ValueError(f"{path}: a config file must hold a mapping of keys, not a list")
        for key, _ in _leaves(loaded, _package(path) + "." if _package(path) else ""):
            set_by[key] = rel
    types = _schema_types()
    groups: dict[str, list[str]] = {}
    for key, value in _leaves(cfg):
        parts = key.split(".")
        group = ".".join(parts[:2]) if parts[0] == "stage" and len(parts) > 2 else parts[0]
        parent = key.rsplit(".", 1)[0]
        desc = explained.get(key) or (f"(of `{parent}`) {explained[parent]}" if parent in explained else "")
        desc = desc.replace("|", "\\|")
        where = f"`conf/{set_by[key]}`" if key in set_by else ""
        row = f"| `{key}` | `{_default(value)}` | {types.get(key, '')} | {where} | {desc} |"
        groups.setdefault(group, []).append(row)
    lines = [
        "# Every config key",
        "",
        "Generated by `python -m pipeline.config_reference` from `conf/` and the config schemas (a test "
        "checks that this page matches them). The defaults are those of a plain `interactavatar` run: "
        "`dataset=synthetic quality=smoke method=interactavatar`; a preset or a method overrides some of "
        "them (the file column says which file sets the value shown). `interactavatar --cfg job` prints "
        "the composed config of any command line.",
        "",
    ]
    for group in sorted(groups, key=lambda g: (g.startswith("stage."), g)):
        lines += [
            f"## `{group}`",
            "",
            "| key | default | type | set in | meaning |",
            "| --- | --- | --- | --- | --- |",
            *groups[group],
            "",
        ]
    for name, composed in (datasets or {}).items():
        lines += _dataset_section(name, composed, types)
    return "\n".join(lines)


def _dataset_section(name: str, composed: DictConfig, types: dict[str, str]) -> list[str]:
    """The keys ``conf/dataset/<name>.yaml`` sets, with their values in ``composed`` (the config composed with
    ``dataset=<name>``) and the file's comments."""
    path = CONF_DIR / "dataset" / f"{name}.yaml"
    explained = dict(_commented_keys(path))
    loaded = OmegaConf.load(path)
    if not isinstance(loaded, DictConfig):
        raise ValueError(f"{path}: a config file must hold a mapping of keys, not a list")
    rows = []
    for key, _ in _leaves(loaded, _package(path) + "." if _package(path) else ""):
        desc = explained.get(key, "").replace("|", "\\|")
        rows.append(f"| `{key}` | `{_default(_node(composed, key))}` | {types.get(key, '')} | {desc} |")
    return [
        f"## `dataset={name}`",
        "",
        f"The keys `conf/dataset/{name}.yaml` sets (`dataset={name}` on the command line); the others are as above.",
        "",
        "| key | value | type | meaning |",
        "| --- | --- | --- | --- |",
        *rows,
        "",
    ]


def _node(cfg: DictConfig, key: str) -> object:
    """The node of dotted ``key`` in ``cfg`` (its value without resolving interpolations or missing values)."""
    parent, _, last = key.rpartition(".")
    container = OmegaConf.select(cfg, parent) if parent else cfg
    return container._get_node(last) if isinstance(container, DictConfig) else None


#: the datasets besides the default whose keys the page lists (``conf/dataset/<name>.yaml``)
OTHER_DATASETS = ("folder", "decaf")


def dataset_configs() -> dict[str, DictConfig]:
    """Name -> the config composed with ``dataset=<name>``, for :data:`OTHER_DATASETS`."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return {name: compose(config_name="config", overrides=[f"dataset={name}"]) for name in OTHER_DATASETS}


def default_config() -> DictConfig:
    """The composed default config, as a plain run sees it (without Hydra's own node)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config")


def main() -> None:
    PAGE.write_text(render(default_config(), dataset_configs()))
    print(f"wrote {PAGE}")


if __name__ == "__main__":
    main()
