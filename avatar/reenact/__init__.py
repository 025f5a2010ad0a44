"""Reenactment: drive a trained avatar with a parameter sequence (its own held-out motion or another actor's)."""

from avatar.reenact.transfer import (
    PLACEMENTS,
    MotionTransfer,
    MotionTransferError,
    head_size,
    parameter_problem,
    transfer_motion,
)

__all__ = ["PLACEMENTS", "MotionTransfer", "MotionTransferError", "head_size", "parameter_problem", "transfer_motion"]
