"""Deterministic synthetic multi-view captures of a person touching their face,
with ground truth (FLAME/MANO parameters, soft-tissue offsets, contact,
keypoints, masks). A pure library: :func:`generate` returns arrays in memory.
"""

from avatar.synthetic.capture import SCENES, SyntheticCapture, SyntheticConfig
from avatar.synthetic.generator import generate

__all__ = ["SCENES", "SyntheticCapture", "SyntheticConfig", "generate"]
