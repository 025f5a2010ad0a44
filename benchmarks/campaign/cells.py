"""The campaign's queue: settings and cells read from a TOML file (``benchmarks/campaign/queue.toml``).

A cell is one training run to measure: a method, trained with one seed on one subject in one setting (overrides of
the app's config), at the campaign's quality preset, then evaluated. Cells of one setting and subject share an
outputs folder, so the shared stages (capture to pbd) are computed once for all their methods and seeds.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from pipeline.workspace import method_run


class QueueError(ValueError):
    """A queue file that cannot be used; the message names the file and what to fix."""


@dataclass(frozen=True)
class Setting:
    """Overrides of the app's config that every cell of the setting runs with, what they mean in words, and the
    commit whose code its cells run (``commit``: a bisect's; None for the newest code)."""

    name: str
    what: str
    overrides: tuple[str, ...]
    commit: str | None = None


@dataclass(frozen=True)
class Cell:
    """One run of the campaign: ``method`` trained with ``seed`` on ``subject`` in ``setting``."""

    setting: str
    subject: str
    method: str
    seed: int

    @property
    def key(self) -> str:
        """``<setting>/<subject>/<method>/seed<k>``: the cell's name in logs, commit messages and the result file."""
        return f"{self.setting}/{self.subject}/{self.method}/seed{self.seed}"

    @property
    def run(self) -> str:
        """The run's folder under ``methods/`` (:func:`pipeline.workspace.method_run`)."""
        return method_run(self.method, self.seed)

    def identity(self) -> tuple[str, str, str, int]:
        return (self.setting, self.subject, self.method, self.seed)


@dataclass(frozen=True)
class Queue:
    """A campaign: its result file's name, the quality preset of every cell, the settings and the cells in order."""

    result: str
    quality: str
    settings: dict[str, Setting]
    cells: tuple[Cell, ...]

    def methods(self) -> list[str]:
        """Every method of the queue, in the order of first appearance."""
        return list(dict.fromkeys(c.method for c in self.cells))


def load_queue(path: Path) -> Queue:
    """The queue in ``path``; :class:`QueueError` naming the file and the fix when it is malformed."""
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise QueueError(f"{path}: cannot read the campaign queue ({err})") from None
    try:
        settings = {
            name: Setting(
                name,
                str(spec["what"]),
                tuple(str(o) for o in spec["overrides"]),
                str(spec["commit"]) if "commit" in spec else None,
            )
            for name, spec in data["settings"].items()
        }
        cells: list[Cell] = []
        for number, group in enumerate(data["cells"], 1):
            unknown = [s for s in group["settings"] if s not in settings]
            if unknown:
                raise QueueError(f"{path}: cells group {number} names settings {unknown} that [settings] lacks")
            for seed in group["seeds"]:
                for subject in group["subjects"]:
                    for setting in group["settings"]:
                        for method in group["methods"]:
                            cell = Cell(str(setting), str(subject), str(method), int(seed))
                            if cell not in cells:
                                cells.append(cell)
        return Queue(str(data["result"]), str(data.get("quality", "draft")), settings, tuple(cells))
    except KeyError as err:
        raise QueueError(f"{path}: the campaign queue lacks the key {err} (see queue.toml)") from None
