"""The dotted keys of a config, and the key a misspelt or misplaced one most likely meant ("did you mean")."""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Any

from omegaconf import DictConfig, OmegaConf

#: How alike (:class:`difflib.SequenceMatcher` ratio) a key and a suggestion must be for the suggestion to be made.
CLOSE = 0.75


def key_paths(node: Any, prefix: str = "") -> list[str]:
    """Every dotted path of the mapping ``node`` (a DictConfig or a dict), its sections and its leaves: ``run``,
    ``run.device``, ...; lists are leaves. Values are not resolved."""
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=False)
    if not isinstance(node, dict):
        return []
    paths = []
    for name, value in node.items():
        path = f"{prefix}{name}"
        paths += [path, *key_paths(value, f"{path}.")]
    return paths


def closest_key(key: str, known: Iterable[str], cutoff: float = CLOSE) -> str | None:
    """The key of ``known`` (dotted paths) that ``key`` most likely meant, or None: the shortest that ends with all of
    ``key``'s components (``evaluate.test_tracking`` -> ``stage.evaluate.test_tracking``), else the one whose last
    components, as many as ``key`` has, are closest to it (``evaluate.test_trackng``; ``subjet`` -> ``subject``),
    else the closest whole path; "close" is a :mod:`difflib` ratio of at least ``cutoff``."""
    candidates = sorted({k for k in known if k != key}, key=lambda k: (k.count("."), len(k), k))
    ending = [k for k in candidates if k.endswith(f".{key}")]
    if ending:
        return ending[0]
    depth = key.count(".") + 1
    tails: dict[str, str] = {}
    for candidate in candidates:  # the shallowest key of each tail
        tails.setdefault(".".join(candidate.split(".")[-depth:]), candidate)
    for pool, lookup in ((list(tails), tails), (candidates, None)):
        near = difflib.get_close_matches(key, pool, n=1, cutoff=cutoff)
        if near:
            return lookup[near[0]] if lookup is not None else near[0]
    return None


def did_you_mean(key: str, known: Iterable[str], cutoff: float = CLOSE) -> str:
    """``"; did you mean <key>?"`` with :func:`closest_key`, or ``""`` when none is close: the end of a message."""
    meant = closest_key(key, known, cutoff)
    return f"; did you mean {meant}?" if meant is not None else ""
