"""What a running stage lends the code it calls (:class:`StageRun`): the pipeline's ``StageRun`` has these
members, and the core names only them, so it never imports the pipeline."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Protocol, TypeVar

from omegaconf import DictConfig

T = TypeVar("T")


class StageRun(Protocol):
    """A stage's run as the representations and the training settings use it.

    Attributes:
        cfg: the whole resolved config.
        out_dir: the stage's fresh output folder.
        scratch_dir: persistent space for checkpoints (None where the stage has none).
        metrics: scalars recorded in the stage's manifest.
        device: the torch device the stage computes on (``cpu``, ``cuda:N``: ``run.device`` resolved).
        precision: ``fp32``, or ``bf16`` for the networks' products (``run.precision``).
    """

    cfg: DictConfig
    out_dir: Path
    scratch_dir: Path | None
    metrics: dict[str, float | int | str]
    device: str
    precision: str

    def input_dir(self, stage: str) -> Path:
        """The artifact folder of the upstream stage ``stage``."""
        ...

    def progress(self, items: Iterable[T], desc: str, total: int | None = None) -> Iterator[T]:
        """``items``, with a progress bar where the run shows them."""
        ...
