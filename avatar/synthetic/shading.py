"""Lighting, shadows and the tone curve of the synthetic studio.

Radiance is computed in linear light: Lambertian reflection of a fixed key
light (shadowed through a shadow map), a fixed fill light and an ambient term,
multiplied by a per-vertex occlusion factor (contact darkening, finger creases)
and the per-sample albedo. It is then encoded with the sRGB OETF (IEC
61966-2-1) and quantised to uint8. The background is a constant linear grey of
:data:`BACKGROUND_LINEAR` (sRGB code value 118).

Per-vertex attribute layout the shader expects (see :class:`Channels`):
canonical position (3, texture space), world position (3), world normal (3),
base albedo (3, linear), occlusion factor (1), pore amplitude (1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from avatar.render.mesh_raster import Mesh, PinholeCamera, Shader, rasterize
from avatar.synthetic.noise import value_noise
from avatar.synthetic.rig import look_at

BACKGROUND_LINEAR = 0.18
#: Direction towards the key light (world): from the subject's right (-x), above, in front.
KEY_DIRECTION = np.array([-0.45, 0.55, 0.70]) / np.linalg.norm([-0.45, 0.55, 0.70])
FILL_DIRECTION = np.array([0.6, 0.1, 0.8]) / np.linalg.norm([0.6, 0.1, 0.8])
KEY_INTENSITY = 0.95
FILL_INTENSITY = 0.30
AMBIENT_INTENSITY = 0.22
#: Pore-scale albedo noise: feature size ~ 1 / PORE_FREQUENCY metres.
PORE_FREQUENCY = 900.0
SHADOW_MAP_SIZE = 512
SHADOW_HALF_WIDTH_M = 0.22
SHADOW_DISTANCE_M = 3.0
SHADOW_BIAS_M = 0.004


class Channels:
    """Slices of the per-vertex attribute vector (C = 14)."""

    CANONICAL = slice(0, 3)
    WORLD = slice(3, 6)
    NORMAL = slice(6, 9)
    ALBEDO = slice(9, 12)
    OCCLUSION = 12
    PORES = 13
    COUNT = 14


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear light (any shape, clipped to [0, 1]) -> uint8 sRGB code values."""
    x = np.clip(linear, 0.0, 1.0)
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(encoded * 255.0).astype(np.uint8)


def srgb_decode(code: np.ndarray) -> np.ndarray:
    """uint8 sRGB code values -> linear light float64 (inverse of :func:`srgb_encode`
    up to quantisation)."""
    x = np.asarray(code, dtype=np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


@dataclass(frozen=True)
class ShadowMap:
    """Depth seen from the key light (a distant pinhole approximating a
    directional light), for percentage-closer shadow lookups.

    Attributes:
        camera: the light's camera.
        depth: (S, S) float32 nearest depth in metres, +inf where empty.
    """

    camera: PinholeCamera
    depth: torch.Tensor

    @staticmethod
    def build(meshes: list[Mesh], target: np.ndarray) -> ShadowMap:
        """Render the shadow map of ``meshes`` around ``target`` (3,) world metres."""
        size = SHADOW_MAP_SIZE
        eye = target + SHADOW_DISTANCE_M * KEY_DIRECTION
        focal = size / 2 * SHADOW_DISTANCE_M / SHADOW_HALF_WIDTH_M
        k = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
        cam = PinholeCamera(K=k, world_to_cam=look_at(eye, target, np.array([0.0, 1.0, 0.0])), width=size, height=size)
        buffer, _ = rasterize(meshes, cam, supersample=1)
        depth = buffer.depth.masked_fill(~buffer.covered, float("inf"))
        return ShadowMap(camera=cam, depth=depth)

    def lit_fraction(self, points: torch.Tensor) -> torch.Tensor:
        """Fraction in [0, 1] of 3x3 shadow-map taps that see ``points`` (N, 3)
        world; points outside the map count as lit."""
        uv, z = self.camera.project(points.to(torch.float64))
        size = self.depth.shape[0]
        col = torch.floor(uv[:, 0]).long()
        row = torch.floor(uv[:, 1]).long()
        lit = torch.zeros(points.shape[0])
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r = (row + dr).clamp(0, size - 1)
                c = (col + dc).clamp(0, size - 1)
                lit += (z.float() - SHADOW_BIAS_M <= self.depth[r, c]).float()
        off_map = (col < 0) | (col >= size) | (row < 0) | (row >= size)
        return torch.where(off_map, torch.ones_like(lit), lit / 9.0)


#: Paints per-sample albedo: (canonical points (N, 3), vertex albedo (N, 3)) -> albedo (N, 3).
Painter = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def make_shader(shadow: ShadowMap, seed: int, painters: dict[int, Painter]) -> Shader:
    """Shader for :func:`avatar.render.mesh_raster.render` over attributes laid out
    as :class:`Channels`; ``painters`` maps a mesh label to its per-sample
    albedo painter. Returns linear radiance (N, 3)."""
    key = torch.as_tensor(KEY_DIRECTION, dtype=torch.float32)
    fill = torch.as_tensor(FILL_DIRECTION, dtype=torch.float32)

    def shade(attrs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """Radiance (N, 3) of covered samples from attributes (N, C) and labels (N,)."""
        normal = torch.nn.functional.normalize(attrs[:, Channels.NORMAL], dim=1, eps=1e-8)
        canonical = attrs[:, Channels.CANONICAL]
        albedo = attrs[:, Channels.ALBEDO].clone()
        for label, paint in painters.items():
            sel = labels == label
            albedo[sel] = paint(canonical[sel], albedo[sel])
        pores = value_noise(canonical, PORE_FREQUENCY, seed)
        albedo = albedo * (1 + attrs[:, Channels.PORES, None] * pores[:, None])
        n_key = (normal @ key).clamp(min=0)
        n_fill = (normal @ fill).clamp(min=0)
        lit = shadow.lit_fraction(attrs[:, Channels.WORLD])
        light = AMBIENT_INTENSITY + KEY_INTENSITY * n_key * lit + FILL_INTENSITY * n_fill
        return albedo * (light * attrs[:, Channels.OCCLUSION])[:, None]

    return shade
