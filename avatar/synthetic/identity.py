"""The synthetic identities: shape coefficients, skin/hair colours and performance style.

Colours are linear-light albedos (the sRGB values they were picked from are in
the comments). Shape coefficients are fixed per identity (independent of the
capture seed) so that train and test sequences show the same person.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Identity:
    """Everything that makes one synthetic subject look like themself.

    Attributes:
        flame_shape: (S,) FLAME identity coefficients.
        mano_shape: (10,) MANO shape coefficients.
        skin: (3,) linear base skin albedo.
        lips: (3,) linear lip albedo.
        brows: (3,) linear eyebrow albedo.
        hair: (3,) linear hair albedo.
        iris: (3,) linear iris albedo.
        texture_seed: seed of the identity's procedural skin noise.
    """

    flame_shape: np.ndarray
    mano_shape: np.ndarray
    skin: np.ndarray
    lips: np.ndarray
    brows: np.ndarray
    hair: np.ndarray
    iris: np.ndarray
    texture_seed: int


def _srgb(r: int, g: int, b: int) -> np.ndarray:
    x = np.array([r, g, b], dtype=np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _shape(seed: int, width: int, scale: float) -> np.ndarray:
    return np.clip(np.random.default_rng(seed).normal(0.0, scale, width), -2.0, 2.0)


def _opposite(a: np.ndarray, b: np.ndarray, magnitude: float) -> np.ndarray:
    """(S,) shape coefficients of ``magnitude`` standard deviations, each on the side opposite to the sum of
    ``a`` and ``b`` (S,): a shape further from both than they are from each other."""
    return -magnitude * np.where(a + b >= 0, 1.0, -1.0)


@dataclass(frozen=True)
class MotionStyle:
    """How a performer acts out the shared scripts (:func:`avatar.synthetic.motion.jitter`).

    Attributes:
        head_gain: multiplies every head key's yaw, pitch and roll (1: the script's angles).
        jitter_gain: multiplies the spread of the seeded per-key variation (angles, curl, spread, tilt).
    """

    head_gain: float = 1.0
    jitter_gain: float = 1.0


def motion_style(subject: str) -> MotionStyle:
    """The performance style of ``subject``: synth_a and synth_b act the scripts as written (they differ by their
    seeded variation only); synth_c turns its head further and varies more from key to key."""
    return MotionStyle(head_gain=1.4, jitter_gain=2.5) if subject == "synth_c" else MotionStyle()


def make_identity(subject: str, num_flame_shape: int) -> Identity:
    """The identity of ``subject`` ("synth_a", "synth_b" or the held-out "synth_c")."""
    if subject == "synth_a":
        return Identity(
            flame_shape=_shape(11, num_flame_shape, 0.9),
            mano_shape=_shape(12, 10, 0.8),
            skin=_srgb(206, 154, 128),
            lips=_srgb(172, 86, 84),
            brows=_srgb(92, 66, 48),
            hair=_srgb(70, 48, 32),
            iris=_srgb(70, 95, 120),
            texture_seed=1001,
        )
    if subject == "synth_b":
        return Identity(
            flame_shape=_shape(21, num_flame_shape, 0.9),
            mano_shape=_shape(22, 10, 0.8),
            skin=_srgb(150, 102, 76),
            lips=_srgb(120, 62, 60),
            brows=_srgb(38, 30, 26),
            hair=_srgb(30, 26, 24),
            iris=_srgb(60, 40, 26),
            texture_seed=2002,
        )
    if subject == "synth_c":  # held out: head and hand on the side of the shape space away from both, a darker skin
        return Identity(
            flame_shape=_opposite(_shape(11, num_flame_shape, 0.9), _shape(21, num_flame_shape, 0.9), 1.5),
            mano_shape=_opposite(_shape(12, 10, 0.8), _shape(22, 10, 0.8), 1.5),
            skin=_srgb(78, 50, 36),
            lips=_srgb(70, 40, 38),
            brows=_srgb(22, 18, 16),
            hair=_srgb(18, 16, 15),
            iris=_srgb(40, 28, 20),
            texture_seed=3003,
        )
    raise ValueError(f"unknown synthetic subject {subject!r} (synth_a, synth_b, synth_c)")
