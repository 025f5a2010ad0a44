"""Which source frames a capture imports: ``dataset.start_frame``, ``dataset.frame_step`` and
``dataset.max_frames`` (shared by the folder and DECAF importers)."""

from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from data_schemas.tables import SchemaError


def selected_frames(num_frames: int, dataset: DictConfig, where: str) -> np.ndarray:
    """Source frame indices (T,) to import from a sequence of ``num_frames`` frames: every
    ``frame_step``-th from ``start_frame``, at most ``max_frames`` of them (null: all).

    Raises SchemaError naming ``where`` (the video or sequence) when a setting is out of range or the
    sequence is shorter than the frames requested (nothing left to import).
    """
    step, start = int(dataset.get("frame_step", 1)), int(dataset.get("start_frame", 0))
    limit = dataset.get("max_frames")
    if step < 1:
        raise SchemaError(f"dataset.frame_step={step}: must be 1 or more")
    if start < 0:
        raise SchemaError(f"dataset.start_frame={start}: must be 0 or more")
    if limit is not None and int(limit) < 1:
        raise SchemaError(f"dataset.max_frames={limit}: must be 1 or more, or null for all frames")
    if start >= num_frames:
        raise SchemaError(
            f"{where}: {num_frames} frames, shorter than the frames requested "
            f"(dataset.start_frame={start}); lower dataset.start_frame or use a longer recording"
        )
    frames = np.arange(start, num_frames, step)
    return frames if limit is None else frames[: int(limit)]
