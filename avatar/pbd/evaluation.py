"""Accuracy of contact offsets against a reference deformation (the synthetic capture's ground truth)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: A vertex "moves" in a frame when its reference or predicted offset exceeds this (metres).
MOVING_THRESHOLD_M = 1e-5


@dataclass(frozen=True)
class VertexErrors:
    """Vertex errors (mm) over the vertices that move in contact frames, for the prediction and for
    zero offsets (the "w/o PBD" baseline), on the same vertices."""

    mean_mm: float
    p95_mm: float
    zero_mean_mm: float
    zero_p95_mm: float
    vertices: int  # (frame, vertex) pairs counted

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def moving_vertex_errors(pred: np.ndarray, ref: np.ndarray, contact: np.ndarray) -> VertexErrors | None:
    """Errors of offsets ``pred`` against ``ref`` (both (T, V, 3) metres) on the contact frames
    (``contact`` (T,) bool), over the vertices that move in the reference *or* the prediction (so a
    dent that spreads too far is penalised too). None when no vertex moves."""
    p, r = np.asarray(pred, np.float64)[contact], np.asarray(ref, np.float64)[contact]
    ref_norm = np.linalg.norm(r, axis=-1)
    moving = (ref_norm > MOVING_THRESHOLD_M) | (np.linalg.norm(p, axis=-1) > MOVING_THRESHOLD_M)
    if not moving.any():
        return None
    err = np.linalg.norm(p - r, axis=-1)[moving] * 1e3
    zero = ref_norm[moving] * 1e3
    return VertexErrors(
        float(err.mean()),
        float(np.percentile(err, 95)),
        float(zero.mean()),
        float(np.percentile(zero, 95)),
        int(moving.sum()),
    )
