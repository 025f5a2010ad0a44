"""Reenactment: drive a trained avatar with a parameter sequence (its own held-out motion or another actor's)."""

from avatar.reenact.transfer import MotionTransferError, head_size, transfer_motion

__all__ = ["MotionTransferError", "head_size", "transfer_motion"]
