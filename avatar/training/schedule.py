"""Learning-rate schedules of 3D Gaussian Splatting."""

from __future__ import annotations

import math


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps`` (3DGS ``get_expon_lr_func``
    without delay); constant after ``max_steps``."""
    if max_steps <= 0 or lr_init == lr_final:
        return lr_init
    t = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


def scaled_interval(fraction: float, total_steps: int, minimum: int = 1) -> int:
    """A schedule point given as a fraction of the run (e.g. densify every 1/300 of it), at least ``minimum``."""
    return max(int(round(fraction * total_steps)), minimum)
