"""Scenes for the Gaussian rasterizer tests: a pinhole camera and random Gaussians in front of it."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

WIDTH, HEIGHT = 24, 20
FOCAL = 30.0


@dataclass
class Scene:
    """Gaussians (N rows) and a camera; ``params()`` are the differentiable inputs in call order."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    K: Tensor
    world_to_cam: Tensor
    width: int
    height: int
    background: Tensor

    def params(self) -> list[Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.colors]

    def camera(self) -> tuple[Tensor, Tensor, int, int, Tensor]:
        return self.K, self.world_to_cam, self.width, self.height, self.background

    def requires_grad_(self) -> Scene:
        for p in self.params():
            p.requires_grad_(True)
        return self

    def cat(self, other: Scene) -> Scene:
        """This scene's Gaussians followed by ``other``'s, with this scene's camera."""
        joined = [torch.cat([a.detach(), b.detach()]) for a, b in zip(self.params(), other.params())]
        return Scene(*joined, *self.camera())


def intrinsics(
    width: int = WIDTH, height: int = HEIGHT, focal: float = FOCAL, dtype: torch.dtype = torch.float64
) -> Tensor:
    """OpenCV K with the principal point at the image centre ((W - 1) / 2, (H - 1) / 2)."""
    return torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def look_from(eye: tuple[float, float, float], dtype: torch.dtype = torch.float64) -> Tensor:
    """A rigid world-to-camera transform (4, 4) for a camera at ``eye`` looking at the origin."""
    eye_t = torch.tensor(eye, dtype=dtype)
    forward = -eye_t / eye_t.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=dtype), forward)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=dtype)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye_t
    return view


def random_scene(
    n: int,
    seed: int,
    width: int = WIDTH,
    height: int = HEIGHT,
    focal: float = FOCAL,
    dtype: torch.dtype = torch.float64,
    max_opacity: float = 1.0,
    scale: float = 0.12,
) -> Scene:
    """N random Gaussians around the origin, seen from a tilted camera at distance ~3.

    Projected sizes are a few pixels, so most Gaussians straddle tile borders.
    """
    g = torch.Generator().manual_seed(seed)
    extent = torch.tensor([width / focal * 1.2, height / focal * 1.2, 0.8])
    means = (torch.rand(n, 3, generator=g) - 0.5) * extent
    quats = torch.randn(n, 4, generator=g)
    scales = (0.15 + torch.rand(n, 3, generator=g)) * scale
    opacities = torch.rand(n, generator=g) * max_opacity
    colors = torch.rand(n, 3, generator=g)
    background = torch.tensor([0.2, 0.5, 0.9])
    tensors = [t.to(dtype) for t in (means, quats, scales, opacities, colors, background)]
    return Scene(
        *tensors[:5],
        K=intrinsics(width, height, focal, dtype),
        world_to_cam=look_from((0.3, -0.2, -3.0), dtype),
        width=width,
        height=height,
        background=tensors[5],
    )


def single_gaussian(
    pixel: tuple[float, float],
    depth: float,
    sigma_px: float,
    opacity: float,
    width: int = WIDTH,
    height: int = HEIGHT,
    dtype: torch.dtype = torch.float64,
) -> Scene:
    """One isotropic Gaussian whose mean projects to ``pixel`` (x, y), identity camera."""
    K = intrinsics(width, height, FOCAL, dtype)
    x = (pixel[0] - K[0, 2]) * depth / FOCAL
    y = (pixel[1] - K[1, 2]) * depth / FOCAL
    s = sigma_px * depth / FOCAL
    return Scene(
        means=torch.tensor([[x, y, depth]], dtype=dtype),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
        scales=torch.full((1, 3), s, dtype=dtype),
        opacities=torch.tensor([opacity], dtype=dtype),
        colors=torch.tensor([[1.0, 0.5, 0.25]], dtype=dtype),
        K=K,
        world_to_cam=torch.eye(4, dtype=dtype),
        width=width,
        height=height,
        background=torch.tensor([0.2, 0.5, 0.9], dtype=dtype),
    )
