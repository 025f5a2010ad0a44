"""What drives the pose-dependent modules of a frame: the conditioning of the hand and face poses and the hand's
relation to the face, per frame and per sequence (InteractAvatar's H and I modules themselves are
:mod:`avatar.representations.bound.dynamic_model`)."""

from avatar.dynamic.conditioning import FrameConditioning, SequenceConditioning, sequence_conditioning

__all__ = ["FrameConditioning", "SequenceConditioning", "sequence_conditioning"]
