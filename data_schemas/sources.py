"""The files a stage reads from outside the artifact tree (a capture folder, the official model files), whose
digests enter its cache key (:mod:`pipeline.sources` hashes them)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig


@dataclass(frozen=True)
class SourceFiles:
    """Files a stage reads from outside the artifact tree.

    Attributes:
        root: the folder they are named relative to in manifests and messages.
        files: absolute paths of every file read (named by their absolute path when outside ``root``).
    """

    root: Path
    files: tuple[Path, ...]


#: what a stage declares: (resolved config, subject) -> its source files (empty when it reads none)
SourceLister = Callable[[DictConfig, str], SourceFiles]
