"""Which frame contact offsets live in, and the conversion at the DECAF boundary.

This project: **world-frame offsets, added** to the posed face, ``v = posed + d_world``
(``deform.parquet``; what the solver returns and every consumer applies).

DECAF: ``deforms.npy`` holds offsets in FLAME's canonical (head) frame that its scripts rotate by
the head's ``global_orient`` ``R_g`` and **subtract**: ``v = posed - R_g d_canonical``. Hence
``d_world = -R_g d_canonical`` (:func:`avatar.templates.decaf.decaf_world_offsets`, used when the
capture adapter imports them) and ``d_canonical = -R_g^T d_world`` (:func:`world_to_decaf_offsets`,
for writing offsets back in DECAF's layout).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def world_to_decaf_offsets(world: np.ndarray, global_orient: np.ndarray) -> np.ndarray:
    """World-frame offsets (T, V, 3) that are added -> DECAF canonical offsets (T, V, 3) that DECAF
    subtracts after rotating them by its head ``global_orient`` (T, 3) axis-angle."""
    R_g = Rotation.from_rotvec(np.asarray(global_orient, dtype=np.float64)).as_matrix()
    return -np.einsum("tji,tvj->tvi", R_g, np.asarray(world, dtype=np.float64))
