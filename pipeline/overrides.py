"""The command line's overrides, checked: Hydra's composition errors and ``+key`` near misses, one line each with the
key that was most likely meant (:func:`data_schemas.key_names.closest_key`).

Hydra composes the config before the app runs, and an override it cannot apply (``evaluate.test_tracking=avatar``:
no such key) ends there; :func:`composition_problem` turns its error into one line. An override with ``+`` adds a
key wherever it is told to, and nothing reads a key added beside the one meant; :func:`added_key_problems` finds
those that are a near miss of a key the app has.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Iterable, Sequence

from hydra.errors import MissingConfigException, OverrideParseException
from omegaconf import DictConfig, OmegaConf

from data_schemas.key_names import did_you_mean, key_paths

#: How alike the name a ``+key`` adds and a key beside it must be for the add to be taken for a typo of it: stricter
#: than a suggestion for a key that does not exist, since it refuses what would otherwise run.
ADDED_CLOSE = 0.85
#: Root sections that are not settings of the app (Hydra's own).
NOT_SETTINGS = ("hydra",)
#: Said where an unknown key has no near miss.
WHERE_KEYS_ARE = "docs/reference/config-keys.md lists the keys, and +key=value adds one of your own"


def setting_paths(cfg: DictConfig) -> list[str]:
    """Every dotted key of the app's settings in ``cfg`` (:func:`key_paths`, Hydra's own section left out)."""
    return [p for p in key_paths(cfg) if p.split(".", 1)[0] not in NOT_SETTINGS]


def override_key(override: str) -> str:
    """The dotted key an override sets, adds or deletes: ``+a.b=1`` -> ``a.b``, ``~a`` -> ``a``."""
    return override.split("=", 1)[0].lstrip("+~")


def _override_of(key: str, overrides: Sequence[str]) -> str:
    """The override of ``overrides`` that names ``key`` (the key itself where none does)."""
    return next((o for o in overrides if override_key(o) == key), key)


def composition_problem(exc: Exception, overrides: Sequence[str], known: Callable[[], Iterable[str]]) -> str:
    """One line for Hydra's error ``exc`` composing the config with the command line's ``overrides``: the override
    and what is wrong with it, with the key or option it most likely meant (``known()``: the config's dotted keys,
    asked only for an unknown key), or Hydra's own message on one line where it is none of those."""
    text = str(exc)
    if found := re.search(r"Could not override '([^']+)'", text):
        key = found[1]
        meant = did_you_mean(key, known())
        return f"{_override_of(key, overrides)}: no such key{meant or f'; {WHERE_KEYS_ARE}'}"
    if found := re.search(r"An item is already at '([^']+)'", text):
        key = found[1]
        return f"{_override_of(key, overrides)}: {key} is set already; set it without the + ({key}=...)"
    if found := re.search(r"Could not delete from config\. '([^']+)' does not exist", text):
        key = found[1]
        return f"{_override_of(key, overrides)}: no such key to delete{did_you_mean(key, known())}"
    if isinstance(exc, MissingConfigException) and exc.options and (found := re.search(r"find '([^']+)'", text)):
        group, _, option = found[1].rpartition("/")
        options = ", ".join(exc.options)
        return f"{group}={option}: no such option of {group} ({options}){did_you_mean(option, exc.options)}"
    if isinstance(exc, OverrideParseException):  # Hydra's message, then where its grammar is described
        return f"{exc.override}: not an override Hydra reads ({' '.join(exc.message.split())})"
    return " ".join(text.split())


def added_key_problems(cfg: DictConfig, named: Sequence[str] = ()) -> list[str]:
    """The ``+key=value`` overrides of this run's command line (``run.overrides``) that add a key nothing reads as a
    near miss of one the app has: beside a key of a close name (``+method.representaton=embedded``), or as a new root
    section whose path is the end of a key's (``+evaluate.test_tracking=avatar``). One line each; a key that a line
    of ``named`` already names (a typed section's unknown key) is left to that line."""
    added = [str(o) for o in OmegaConf.select(cfg, "run.overrides", default=None) or () if _adds(str(o))]
    keys = [override_key(o) for o in added]
    others = _paths_without(setting_paths(cfg), keys)
    problems = []
    for override, key in zip(added, keys, strict=True):
        if any(line.startswith((f"{key}:", f"{key}=")) for line in named):
            continue
        meant = _added_near_miss(key, others)
        if meant is not None:
            problems.append(f"{override}: adds {key}, which nothing reads; did you mean {meant}?")
    return problems


def _paths_without(paths: list[str], keys: list[str]) -> set[str]:
    """The dotted ``paths`` of a config as they were before ``keys`` were added: those that lead to a leaf (a
    value, an empty section) not at or below one of ``keys``."""
    parents = {p.rpartition(".")[0] for p in paths}
    kept: set[str] = set()
    for path in paths:
        if path in parents or any(path == k or path.startswith(f"{k}.") for k in keys):
            continue
        parts = path.split(".")
        kept.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return kept


def _adds(override: str) -> bool:
    """Whether ``override`` adds a key (``+key=value``; not ``++``, which adds or overrides)."""
    return override.startswith("+") and not override.startswith("++")


def _added_near_miss(key: str, others: set[str]) -> str | None:
    """The key of ``others`` (the config's keys but the added ones) that adding ``key`` most likely meant, or None."""
    if key.split(".", 1)[0] not in others:  # a new root section: a key elsewhere that ends as this one does
        ending = sorted((p for p in others if p.endswith(f".{key}")), key=len)
        if ending:
            return ending[0]
    parent, _, leaf = key.rpartition(".")
    siblings = {p.rpartition(".")[2]: p for p in others if p.rpartition(".")[0] == parent}
    near = difflib.get_close_matches(leaf, list(siblings), n=1, cutoff=ADDED_CLOSE)
    return siblings[near[0]] if near else None
