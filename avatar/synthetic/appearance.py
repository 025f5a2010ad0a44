"""Procedural albedo and per-vertex occlusion of the face and the hand.

* Albedo (linear, per vertex): an identity's base skin colour with
  low-frequency blotches (redness varying over ~4 cm) and mid-frequency
  mottling; on the hand the palm is lighter and pinker, the back a little
  darker and the nails lighter. The face's small features (lips, brows, eyes,
  hair) are painted per sample by :mod:`avatar.synthetic.face_paint`, and
  pore-scale noise is added per sample by the shader; each vertex carries its
  pore amplitude.
* Occlusion (multiplies all light, in (0, 1]):
  - contact darkening of the face (and the hand) near the other mesh, growing
    with proximity (an ambient-occlusion stand-in),
  - finger creases: a narrow dark band across every flexed joint, deeper on the
    palmar side, growing with the joint's bend,
  - curl self-shadow: palmar surfaces of the palm and fingers darken as the
    fingers curl over them.

Texture coordinates are the template's rest positions (solid texture), so the
pattern moves with the skin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from avatar.synthetic.geometry import vertex_normals
from avatar.synthetic.hand_pose import FINGER_CHAINS, HandFrame
from avatar.synthetic.identity import Identity
from avatar.synthetic.noise import fbm
from avatar.templates.model import TemplateModel

PORE_AMPLITUDE = 0.07
CONTACT_AO_SIGMA_M = 0.012
FACE_CONTACT_AO = 0.45
HAND_CONTACT_AO = 0.25
CREASE_HALF_WIDTH_M = 0.0022
CREASE_DEPTH_PALMAR = 0.55
CREASE_DEPTH_DORSAL = 0.25
CURL_SHADOW = 0.35
#: appearance "pressed": a dent this deep (metres) blanches the skin fully; how far it goes towards pale
BLANCH_FULL_DEPTH_M = 0.004
BLANCH_STRENGTH = 0.6
#: the colour pressed skin goes towards, relative to its own mean: lighter, less red, a little yellow
BLANCH_TINT = np.array([1.18, 1.16, 1.02])


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def skin_variation(rest: np.ndarray, base: np.ndarray, seed: int) -> np.ndarray:
    """(V, 3) skin albedo: ``base`` (3,) with blotches and mottling at the rest
    positions (V, 3) metres."""
    p = torch.from_numpy(np.array(rest, dtype=np.float64))
    blotch = fbm(p, 25.0, 3, seed).numpy()[:, None]
    mottle = fbm(p, 140.0, 2, seed + 7).numpy()[:, None]
    tint = np.array([0.10, -0.06, -0.08])  # redder where blotch > 0
    return base * (1.0 + blotch * tint + 0.05 * mottle)


def _region_mix(albedo: np.ndarray, ids: np.ndarray, colour: np.ndarray, weight: np.ndarray | float) -> None:
    """Blend ``colour`` into ``albedo`` rows ``ids`` with ``weight`` (in place)."""
    w = np.broadcast_to(np.asarray(weight, dtype=np.float64), ids.shape)[:, None]
    albedo[ids] = (1 - w) * albedo[ids] + w * colour


@dataclass(frozen=True)
class HandAppearance:
    """Static appearance data of one identity's hand (rest pose).

    Attributes:
        albedo: (Vh, 3) linear albedo.
        pores: (Vh,) pore noise amplitude.
        crease: (15, Vh) weight of each joint's crease band at each vertex
            (0 away from the joint, 1 on it), already scaled by palmar/dorsal depth.
        palmar: (Vh,) in [0, 1], how much a vertex faces the palm side.
        digit: (Vh,) int, 0 palm, 1..5 thumb .. pinky.
    """

    albedo: np.ndarray
    pores: np.ndarray
    crease: np.ndarray
    palmar: np.ndarray
    digit: np.ndarray

    @staticmethod
    def build(
        model: TemplateModel, identity: Identity, frame: HandFrame, rest: np.ndarray, joints: np.ndarray
    ) -> HandAppearance:
        """From the template, the identity, the hand frame and the shaped rest
        vertices (Vh, 3) and joints (16, 3)."""
        labels = model.part_labels or {}
        normals = vertex_normals(torch.as_tensor(rest), torch.from_numpy(np.array(model.faces))).numpy()
        facing = normals @ frame.palm  # +1 palmar, -1 dorsal
        palmar = _smoothstep(-0.1, 0.5, facing)
        digit = np.zeros(rest.shape[0], dtype=np.int64)
        for k, name in enumerate(("thumb", "index", "middle", "ring", "pinky")):
            digit[labels.get(name, np.zeros(0, np.int64))] = k + 1
        albedo = skin_variation(rest, identity.skin, identity.texture_seed + 1)
        albedo *= 1 + palmar[:, None] * np.array([0.10, 0.02, 0.02]) - (1 - palmar[:, None]) * 0.05
        tips = labels.get("fingertips", np.zeros(0, np.int64))
        nail = _smoothstep(0.45, 0.8, -facing[tips])
        nail_colour = np.clip(identity.skin * np.array([1.25, 1.2, 1.25]) + 0.08, 0.0, 0.9)
        _region_mix(albedo, tips, nail_colour, nail)
        pores = np.full(rest.shape[0], PORE_AMPLITUDE)
        pores[tips] *= 1 - nail
        crease = np.zeros((15, rest.shape[0]))
        depth = CREASE_DEPTH_DORSAL + (CREASE_DEPTH_PALMAR - CREASE_DEPTH_DORSAL) * palmar
        for f, chain in enumerate(FINGER_CHAINS):
            on_digit = digit == f + 1
            for j in chain:
                bone = np.cross(frame.palm, frame.flex_axes[j - 1])  # along the bone
                axial = (rest - joints[j]) @ bone
                band = np.exp(-0.5 * (axial / CREASE_HALF_WIDTH_M) ** 2)
                # A finger's first crease sits on the palm side of the web too.
                reach = on_digit | (
                    (digit == 0) & (j == chain[0]) & (f > 0) & (np.linalg.norm(rest - joints[j], axis=1) < 0.02)
                )
                crease[j - 1] = band * depth * reach
        return HandAppearance(albedo=albedo, pores=pores, crease=crease, palmar=palmar, digit=digit)

    def pose_occlusion(self, curl: np.ndarray, bend: np.ndarray) -> np.ndarray:
        """(Vh,) occlusion factor for a pose: ``bend`` (15,) flexion angle of
        joints 1..15 (radians), ``curl`` (5,) finger curl, thumb .. pinky."""
        crease = np.clip(bend, 0.0, 1.6) @ self.crease / 1.6
        curl = np.clip(curl, 0.0, 1.6) / 1.6
        own = np.concatenate(([curl[1:].mean()], curl))[self.digit]  # the palm takes the fingers' mean
        shadow = CURL_SHADOW * own * self.palmar
        return np.clip((1 - crease) * (1 - shadow), 0.05, 1.0)


def contact_occlusion(face: np.ndarray, hand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Proximity darkening ((Vf,), (Vh,) factors in (0, 1]) of face vertices (Vf, 3)
    near the hand (Vh, 3) and vice versa (world metres)."""
    reach = 4 * CONTACT_AO_SIGMA_M
    d_face, _ = cKDTree(hand).query(face, distance_upper_bound=reach)
    d_hand, _ = cKDTree(face).query(hand, distance_upper_bound=reach)

    def falloff(d: np.ndarray) -> np.ndarray:
        return np.where(np.isfinite(d), np.exp(-0.5 * (np.minimum(d, reach) / CONTACT_AO_SIGMA_M) ** 2), 0.0)

    return 1 - FACE_CONTACT_AO * falloff(d_face), 1 - HAND_CONTACT_AO * falloff(d_hand)


def pressure_blanching(albedo: np.ndarray, dent: np.ndarray) -> np.ndarray:
    """(V, 3) albedo of skin pressed by ``dent`` (V,) metres deep: blood pushed out of the capillaries leaves it
    paler and yellower, blending towards :data:`BLANCH_TINT` times the albedo's grey, in proportion to the depth up
    to :data:`BLANCH_FULL_DEPTH_M`. ``albedo`` (V, 3) linear; zero depth leaves it unchanged."""
    weight = BLANCH_STRENGTH * np.clip(dent / BLANCH_FULL_DEPTH_M, 0.0, 1.0)[:, None]
    pale = albedo.mean(axis=1, keepdims=True) * BLANCH_TINT
    return (1 - weight) * albedo + weight * pale


def face_appearance(model: TemplateModel, identity: Identity) -> tuple[np.ndarray, np.ndarray]:
    """Face albedo (Vf, 3) and pore amplitude (Vf,) of an identity on the head template."""
    rest = np.asarray(model.v_template)
    albedo = skin_variation(rest, identity.skin, identity.texture_seed)
    pores = np.full(rest.shape[0], PORE_AMPLITUDE)
    return albedo, pores
