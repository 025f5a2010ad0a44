"""A whole sequence's contact deformation with one report row per frame (the pbd and reenact stages)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from avatar.pbd.problem import PBDConfig
from avatar.pbd.solver import solve_sequence


@dataclass
class SequenceDeformation:
    """One sequence: offsets (T, V, 3) metres (world, added to the posed face), face (T, V) and hand (T, Vh)
    contact flags, one report row per frame, and the wall time (s) of each simulated frame."""

    offsets: np.ndarray
    face_contact: np.ndarray
    hand_contact: np.ndarray
    frames: list[dict] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)


def simulate_sequence(
    face: torch.Tensor,
    hand: torch.Tensor,
    faces: torch.Tensor,
    hand_faces: torch.Tensor,
    stiffness: torch.Tensor,
    cfg: PBDConfig,
) -> SequenceDeformation:
    """XPBD on every frame of the posed face (T, V, 3) and hand (T, Vh, 3) (warm-started from the previous
    frame if configured); report rows: frame, near, simulated, iterations, free and contact vertices,
    residual penetration (max, mean) and the largest offset, in millimetres."""
    results = solve_sequence(face, hand, faces, hand_faces, stiffness, cfg)
    out = SequenceDeformation(
        np.stack([r.offsets.numpy() for r in results]),
        np.stack([r.face_contact.numpy() for r in results]),
        np.stack([r.hand_contact.numpy() for r in results]),
        seconds=[r.seconds for r in results if r.simulated],
    )
    out.frames = [
        {
            "frame": t,
            "near": r.near,
            "simulated": r.simulated,
            "iterations": r.iterations,
            "free_vertices": r.free_vertices,
            "contact_vertices": int(r.face_contact.sum()),
            "penetration_max_mm": r.penetration_max_m * 1e3,
            "penetration_mean_mm": r.penetration_mean_m * 1e3,
            "max_offset_mm": r.max_offset_m * 1e3,
        }
        for t, r in enumerate(results)
    ]
    return out
