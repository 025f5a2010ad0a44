"""In-memory training data: the multi-view crops of a sequence (the posed meshes are :mod:`avatar.posing`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from avatar.device import to_device

FACE_LABEL, HAND_LABEL = 1, 2  # part labels of the crops' masks (see ViewSet)
UNOBSERVED_LABEL = 4  # crop padding past the camera image (data_schemas.frames.UNOBSERVED)


@dataclass
class ViewSet:
    """Square crops of one sequence seen by C cameras over T frames.

    Attributes:
        images: (T, C, S, S, 3) uint8 sRGB crops (converted to float per sample, to keep memory low).
        labels: (T, C, S, S) uint8 part labels (0 background, 1 face, 2 hand, 3 unknown foreground,
            4 unobserved: crop padding past the camera image, never compared with a render).
        K: (C, 3, 3) crop intrinsics (OpenCV pixel convention).
        world_to_cam: (C, 4, 4) extrinsics.
        camera_ids: the C camera names.
        background: (3,) float background colour in [0, 1].
    """

    images: Tensor
    labels: Tensor
    K: Tensor
    world_to_cam: Tensor
    camera_ids: list[str]
    background: Tensor

    @property
    def num_frames(self) -> int:
        return self.images.shape[0]

    def to(self, device: torch.device | str) -> ViewSet:
        """The same crops on ``device`` (this set itself where they are there already)."""
        return to_device(self, device)

    @property
    def num_cameras(self) -> int:
        return self.images.shape[1]

    @property
    def size(self) -> int:
        return self.images.shape[2]

    def image(self, frame: int, camera: int) -> Tensor:
        """(S, S, 3) float image in [0, 1]."""
        return self.images[frame, camera].float() / 255.0

    def observed(self, frame: int, camera: int) -> Tensor:
        """(S, S) bool: the pixels the camera saw (False on crop padding past its image)."""
        return self.labels[frame, camera] != UNOBSERVED_LABEL

    def target_and_render(self, pred: Tensor, frame: int, camera: int) -> tuple[Tensor, Tensor]:
        """(ground truth, render) of crop (``frame``, ``camera``) for a loss or metric, both (S, S, 3) in
        ``pred``'s dtype: on unobserved pixels the render is replaced by the ground truth, so they add
        nothing to any image term and pass it no gradient (the padding's colour is not what the camera
        would have seen there)."""
        gt = self.image(frame, camera).to(pred.dtype)
        return gt, torch.where(self.observed(frame, camera)[..., None], pred, gt)

    def cameras(self, camera_ids: list[str]) -> ViewSet:
        """The crops of the cameras ``camera_ids`` alone, in that order (the same tensors' rows, not copies of
        the whole set); an unknown id is a ValueError."""
        unknown = sorted(set(camera_ids) - set(self.camera_ids))
        if unknown:
            raise ValueError(f"cameras {unknown} are not among {self.camera_ids}")
        index = torch.tensor([self.camera_ids.index(c) for c in camera_ids], dtype=torch.long)
        return replace(
            self,
            images=self.images[:, index],
            labels=self.labels[:, index],
            K=self.K[index],
            world_to_cam=self.world_to_cam[index],
            camera_ids=list(camera_ids),
        )
