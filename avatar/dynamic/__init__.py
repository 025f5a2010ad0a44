"""The InteractAvatar model after the warm-up: pose-dependent hand MLPs and hand-face interaction MLPs."""

from avatar.dynamic.conditioning import FrameConditioning, SequenceConditioning, sequence_conditioning
from avatar.dynamic.model import DynamicAvatar, DynamicFrame, DynamicModelConfig, interaction_weights

__all__ = [
    "DynamicAvatar",
    "DynamicFrame",
    "DynamicModelConfig",
    "FrameConditioning",
    "SequenceConditioning",
    "interaction_weights",
    "sequence_conditioning",
]
