"""Per-sample painted facial features: eyes, lips, brows and hair.

The head template is far too coarse (a few millimetres between vertices) to
carry an iris or a lip border per vertex, so these features are painted per
render sample from the sample's *canonical* position (its point on the rest
template), in the head's direction space: ``yaw = atan2(x, z)``,
``pitch = atan2(y, hypot(x, z))`` about the template origin (the skull
centre). Region outlines come from the template's own 68 landmarks (iBUG
order), so they follow the template's design:

* eyes: inside each eye contour (landmarks 36-41, 42-47): sclera, an iris disc
  and a pupil centred in the contour;
* lips: inside the outer lip contour (48-59), darker inside the inner contour
  (60-67, the mouth line);
* brows: a tapered band along the brow landmarks (17-21, 22-26) with
  hair-like streak noise;
* hair: above a hairline that starts a few centimetres above the brows and
  falls to the nape behind the head, with streak noise.

Painted colours replace the vertex albedo where a region's weight is 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatar.synthetic.identity import Identity
from avatar.synthetic.noise import fbm
from avatar.templates.layers import FLAMELayer

SCLERA = (0.60, 0.56, 0.52)
PUPIL = (0.012, 0.010, 0.010)
MOUTH_LINE = 0.25  # inner-mouth darkening factor of the lip colour
IRIS_RADIUS = 0.050  # direction-space radians
PUPIL_RADIUS = 0.020
BROW_HALF_WIDTH = (0.030, 0.014)  # medial, lateral (radians of pitch)
#: Hairline pitch (radians) against |yaw|: above the forehead, down the temples, to the nape.
HAIRLINE_YAW = (0.0, 0.5, 0.9, 1.3, 1.7, np.pi)
HAIRLINE_PITCH = (0.98, 0.93, 0.72, 0.30, -0.30, -0.55)
HAIRLINE_JITTER = 0.03


def direction_space(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) canonical points -> yaw (N,), pitch (N,) radians about the template origin."""
    x, y, z = points.unbind(-1)
    return torch.atan2(x, z), torch.atan2(y, torch.hypot(x, z))


def _inside(yaw: torch.Tensor, pitch: torch.Tensor, polygon: torch.Tensor) -> torch.Tensor:
    """Even-odd point-in-polygon test of (yaw, pitch) against polygon (K, 2)."""
    inside = torch.zeros_like(yaw, dtype=torch.bool)
    for k in range(polygon.shape[0]):
        (x0, y0), (x1, y1) = polygon[k - 1], polygon[k]
        crosses = (y0 > pitch) != (y1 > pitch)
        x_at = x0 + (pitch - y0) * (x1 - x0) / (y1 - y0 + 1e-12)
        inside ^= crosses & (yaw < x_at)
    return inside


def _mix(base: torch.Tensor, colour: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    w = weight[:, None]
    return base * (1 - w) + colour * w


@dataclass(frozen=True)
class FacePaint:
    """Painted features of one identity on one head template.

    Attributes:
        eyes: two (6, 2) eye contours in direction space.
        lips_outer: (12, 2) outer lip contour; lips_inner: (8, 2) inner contour.
        brows: two (5, 2) brow polylines.
        identity: colours and texture seed.
    """

    eyes: tuple[torch.Tensor, torch.Tensor]
    lips_outer: torch.Tensor
    lips_inner: torch.Tensor
    brows: tuple[torch.Tensor, torch.Tensor]
    identity: Identity

    @staticmethod
    def build(flame: FLAMELayer, identity: Identity) -> FacePaint:
        """Outlines from the landmarks of ``flame``'s rest template."""
        lmk = flame.landmarks(flame.v_template[None])[0].float()
        yaw, pitch = direction_space(lmk)
        pts = torch.stack([yaw, pitch], dim=1)
        return FacePaint(
            eyes=(pts[36:42], pts[42:48]),
            lips_outer=pts[48:60],
            lips_inner=pts[60:68],
            brows=(pts[17:22], pts[22:27]),
            identity=identity,
        )

    def _brow_weight(self, yaw: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
        """(N,) brow coverage in [0, 1] of direction-space points."""
        weight = torch.zeros_like(yaw)
        for line in self.brows:
            order = torch.argsort(line[:, 0])
            ys, ps = line[order, 0], line[order, 1]
            t = ((yaw - ys[0]) / (ys[-1] - ys[0])).clamp(0, 1)
            # Piecewise-linear centre line, widest at the medial end (nearer yaw 0).
            centre = torch.from_numpy(np.interp(yaw.numpy(), ys.numpy(), ps.numpy())).float()
            medial = 1 - t if abs(float(ys[0])) < abs(float(ys[-1])) else t
            half = BROW_HALF_WIDTH[1] + (BROW_HALF_WIDTH[0] - BROW_HALF_WIDTH[1]) * medial
            span = ((yaw - ys[0]) * (ys[-1] - yaw) >= 0).float()
            band = (1 - ((pitch - centre) / half).abs()).clamp(0, 1) ** 0.5
            weight = torch.maximum(weight, band * span)
        return weight

    def _hair_and_brows(
        self, canonical: torch.Tensor, yaw: torch.Tensor, pitch: torch.Tensor, out: torch.Tensor
    ) -> None:
        """Paint hair above the (noisy) hairline and the brows, with streak noise."""
        ident, seed = self.identity, self.identity.texture_seed
        line = torch.from_numpy(np.interp(yaw.abs().numpy(), HAIRLINE_YAW, HAIRLINE_PITCH)).float()
        brow_lo = min(float(b[:, 1].min()) for b in self.brows) - BROW_HALF_WIDTH[0]
        brow_hi = max(float(b[:, 1].max()) for b in self.brows) + BROW_HALF_WIDTH[0]
        idx = torch.nonzero((pitch > line - HAIRLINE_JITTER) | ((pitch > brow_lo) & (pitch < brow_hi))).squeeze(1)
        p, y, q = canonical[idx], yaw[idx], pitch[idx]
        hair = ((q - line[idx] - HAIRLINE_JITTER * fbm(p, 60.0, 2, seed + 37)) / 0.04).clamp(0, 1)
        streaks = fbm(p * torch.tensor([1.0, 0.15, 1.0]), 700.0, 2, seed + 31)  # vertical streaks
        hair_colour = torch.as_tensor(ident.hair, dtype=torch.float32) * (1 + 0.45 * streaks[:, None])
        painted = _mix(out[idx], hair_colour, hair)
        brow = (self._brow_weight(y, q) * (0.75 + 0.25 * streaks)).clamp(0, 1)
        out[idx] = _mix(painted, torch.as_tensor(ident.brows, dtype=torch.float32), brow)

    @staticmethod
    def _in_bounds(yaw: torch.Tensor, pitch: torch.Tensor, polygon: torch.Tensor) -> torch.Tensor:
        """Indices of the points inside the polygon's bounding box."""
        lo, hi = polygon.amin(dim=0), polygon.amax(dim=0)
        return torch.nonzero((yaw >= lo[0]) & (yaw <= hi[0]) & (pitch >= lo[1]) & (pitch <= hi[1])).squeeze(1)

    def _lips(self, yaw: torch.Tensor, pitch: torch.Tensor, out: torch.Tensor) -> None:
        """Paint the lips, darker inside the mouth line."""
        idx = self._in_bounds(yaw, pitch, self.lips_outer)
        y, q = yaw[idx], pitch[idx]
        colour = torch.as_tensor(self.identity.lips, dtype=torch.float32).expand(idx.numel(), 3)
        colour = colour * (1 - (1 - MOUTH_LINE) * _inside(y, q, self.lips_inner).float())[:, None]
        out[idx] = _mix(out[idx], colour, 0.9 * _inside(y, q, self.lips_outer).float())

    def _eyes(self, yaw: torch.Tensor, pitch: torch.Tensor, out: torch.Tensor) -> None:
        """Paint sclera, iris and pupil inside each eye contour."""
        for contour in self.eyes:
            idx = self._in_bounds(yaw, pitch, contour)
            y, q = yaw[idx], pitch[idx]
            centre = contour.mean(dim=0)
            r = torch.hypot(y - centre[0], q - centre[1])
            eye = _mix(
                torch.as_tensor(SCLERA).expand(idx.numel(), 3),
                torch.as_tensor(self.identity.iris, dtype=torch.float32),
                (r < IRIS_RADIUS).float(),
            )
            eye = _mix(eye, torch.as_tensor(PUPIL).expand(idx.numel(), 3), (r < PUPIL_RADIUS).float())
            out[idx] = _mix(out[idx], eye, _inside(y, q, contour).float())

    def __call__(self, canonical: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
        """Paint features over ``albedo`` (N, 3) at canonical points (N, 3); each
        feature only touches the samples inside its direction-space bounds."""
        yaw, pitch = direction_space(canonical)
        out = albedo.clone()
        self._hair_and_brows(canonical, yaw, pitch, out)
        self._lips(yaw, pitch, out)
        self._eyes(yaw, pitch, out)
        return out
