"""``hydra/sweeper=interactavatar``: Hydra's basic sweeper that composes every job's config once, in the driver,
checks each and hands each job its own, and names the jobs that failed in one line each (:mod:`pipeline.batch`)."""

from __future__ import annotations

from pipeline.batch import CheckedSweeper


class BatchSweeper(CheckedSweeper):
    """:class:`pipeline.batch.CheckedSweeper` where Hydra finds plugins (the class Hydra instantiates by name)."""
