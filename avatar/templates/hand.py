"""A procedural right hand with the MANO layout (16 joints, 45 pose dims, 10 betas).

Rest pose and axes (metres): wrist joint near the origin, flat hand, fingers
along +x, back of the hand +y (palm faces -y), thumb on the -z side (anatomical
right hand), middle fingertip at x ~ 0.186, palm ~ 8.3 cm wide.

Surface: a closed quad mesh built from generalised tubes. The palm is one tube
along x capped at the wrist; its distal ring splits into the four finger tubes
through three "web" vertices; the thumb tube grows out of a 3 x 3 hole on the
radial-palmar side of the palm; every digit ends in a dome whose apex vertex is
that digit's fingertip (``tip_vertex_ids``). Each digit ring has 12 vertices,
the palm ring 36. Joints sit on the digit axes and are regressed
exactly from nearby vertices. Skinning weights are a soft-min of distances to
the bones (each vertex only sees the wrist and its own digit's joints).

Pose correctives (``posedirs``): for every digit joint, flexion by phi raises a
dorsal knuckle bulge ``(1 - cos phi) * 0.2 r``, stretches the palmar crease
along the bone by ``(1 - cos phi) * 0.5 * (s - s_joint)`` (against the
linear-blend collapse of the inner side) and bulges the palmar soft tissue by
``sin phi * 0.12 r`` (r: digit radius), all fading over ~0.7 r along the bone.

Shape space (``shapedirs``, 10 columns, beta = 1 moves the skin by a few mm):
0 size, 1 finger length, 2 palm width, 3 finger thickness, 4 palm thickness,
5 palm length, 6 thumb length, 7 thumb thickness, 8 fingertip fullness,
9 palmar padding.

Pose PCA (``hands_components``): an orthonormal 45 x 45 basis whose first rows
are the synergies curl-all, spread, thumb opposition, pinch (thumb + index) and
fist-but-index; ``hands_mean`` is a slightly relaxed curl.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from avatar.templates.meshing import MeshBuilder, ring_quads
from avatar.templates.model import TemplateModel
from avatar.templates.rigging import (
    axis_corrective,
    joint_regressor,
    orthonormal_completion,
    segment_distance,
    smooth_weights,
    smoothstep,
    softmin_weights,
)

NUM_JOINTS = 16
MANO_PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)
DIGIT_NAMES = ("thumb", "index", "middle", "ring", "pinky")
PALM_PART = 0  # vertex part ids: 0 palm, 1 + digit index (thumb, index, middle, ring, pinky)

_RING_VERTS = 12  # digit ring: top row 5, side, bottom row 5, side
_N_COL = 4  # palm columns per finger -> palm ring of 8 * 4 + 4 = 36
_RING_STEP = 0.0036  # spacing of digit rings (m)
_WEB_OFFSET = 0.012  # finger webs lie this far distal of the MCP joints
_TIP_BONE_GAP = 0.006  # distal phalanx ends this far before the skin tip
_TAU = 0.0025  # skinning soft-min temperature (m)
_SMOOTH_ITERS = 2  # Laplacian smoothing passes over the skinning weights


@dataclass(frozen=True)
class _Digit:
    name: str
    joints: tuple[int, int, int]
    first_joint: np.ndarray  # (3,) MCP (fingers) / CMC (thumb)
    direction: np.ndarray  # (3,) unit bone direction in the rest pose
    dorsal: np.ndarray  # (3,) unit, perpendicular to direction, nail side
    lengths: tuple[float, float, float]  # bone lengths, the last one to the skin tip
    radii: tuple[float, float]  # skin radius at the digit base and at the tip

    @property
    def length(self) -> float:
        return float(sum(self.lengths))

    @property
    def joint_positions(self) -> np.ndarray:
        """(4, 3): the three joints and the skin tip."""
        steps = np.concatenate(([0.0], np.cumsum(self.lengths)))
        return self.first_joint + steps[:, None] * self.direction

    @property
    def flex_axis(self) -> np.ndarray:
        """Positive rotation about this axis curls the digit toward the palm."""
        return np.cross(self.dorsal, self.direction)

    def radius(self, s: npt.ArrayLike) -> np.ndarray:
        """Skin radius at arc length s from the first joint, with knuckle bulges."""
        r0, r1 = self.radii
        s = np.asarray(s, dtype=np.float64)
        base = r0 + (r1 - r0) * np.clip(s / self.length, 0.0, 1.0)
        knuckles = sum(np.exp(-0.5 * ((s - k) / 0.004) ** 2) for k in np.cumsum(self.lengths)[:2])
        return base * (1.0 + 0.04 * knuckles)


def _unit(v: npt.ArrayLike) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _finger(
    name: str,
    joints: tuple[int, int, int],
    z: float,
    mcp_x: float,
    splay: float,
    lengths: tuple[float, float, float],
    radii: tuple[float, float],
) -> _Digit:
    direction = np.array([np.cos(splay), 0.0, np.sin(splay)])
    return _Digit(name, joints, np.array([mcp_x, 0.0, z]), direction, np.array([0.0, 1.0, 0.0]), lengths, radii)


# Fingers in palm order (-z to +z); MANO joint ids 1-3 index, 4-6 middle, 10-12 ring, 7-9 pinky.
_FINGERS = (
    _finger("index", (1, 2, 3), -0.0265, 0.090, -0.07, (0.040, 0.024, 0.021), (0.0095, 0.0080)),
    _finger("middle", (4, 5, 6), -0.0065, 0.093, 0.00, (0.044, 0.028, 0.021), (0.0098, 0.0082)),
    _finger("ring", (10, 11, 12), 0.0130, 0.090, 0.06, (0.041, 0.027, 0.021), (0.0092, 0.0077)),
    _finger("pinky", (7, 8, 9), 0.0310, 0.083, 0.13, (0.032, 0.020, 0.019), (0.0080, 0.0067)),
)
_THUMB_DIRECTION = _unit([0.72, -0.18, -0.67])
_THUMB_DORSAL_HINT = np.array([0.0, 0.55, -0.83])
_THUMB_LENGTHS = (0.042, 0.032, 0.027)
_THUMB_RADII = (0.0125, 0.0095)
_THUMB_BASE_DEPTH = 0.014  # CMC joint this far inside the palm along the thumb axis

# Palm tube: ring parameters t in [0, 1] (x = t * distal x); rings 2..5 frame the thumb hole.
_PALM_T = np.concatenate(([0.0, 0.1, 0.2, 0.29, 0.38], np.linspace(0.47, 1.0, 10)))
_HOLE_RINGS = (2, 5)
_HOLE_COLUMNS = (32, 35)  # palm ring vertex ids B2, B1, B0, S_left (radial-palmar side)


def _palm_profile(t: float) -> tuple[float, float, float]:
    """Half width, dorsal half thickness, palmar half thickness at palm parameter t."""
    width = float(np.interp(t, [0.0, 0.35, 1.0], [0.029, 0.038, 0.0415]))
    dorsal = float(np.interp(t, [0.0, 0.4, 1.0], [0.016, 0.012, 0.0105]))
    palmar = float(np.interp(t, [0.0, 0.4, 1.0], [0.017, 0.0145, 0.012]))
    return width, dorsal, palmar


def _palm_lateral_stations() -> np.ndarray:
    """(4 n_col + 1,) normalised lateral positions u of the top / bottom rows; the
    column boundaries are the finger webs so each finger owns n_col columns."""
    width = _palm_profile(1.0)[0]
    centres = np.array([f.first_joint[2] for f in _FINGERS])
    bounds = np.concatenate(([-0.95 * width], 0.5 * (centres[1:] + centres[:-1]), [0.95 * width])) / width
    return np.concatenate([np.linspace(a, b, _N_COL + 1)[:-1] for a, b in zip(bounds[:-1], bounds[1:])] + [bounds[-1:]])


def _palm_rings() -> np.ndarray:
    """(R, 36, 3) palm rings, wrist to finger webs. Ring layout: top row (u = -0.95..0.95,
    dorsal), right side (+z), bottom row reversed (palmar), left side (-z)."""
    u = _palm_lateral_stations()
    centres_u = np.array([f.first_joint[2] for f in _FINGERS]) / _palm_profile(1.0)[0]
    base_x = np.array([f.first_joint[0] + _WEB_OFFSET for f in _FINGERS])
    ring_u = np.concatenate((u, [1.0], u[::-1], [-1.0]))
    shape = np.concatenate((np.ones(u.size), [0.0], -np.ones(u.size), [0.0]))  # +1 dorsal, -1 palmar, 0 side
    x_end = np.interp(ring_u, centres_u, base_x)
    lift = (1.0 - np.abs(ring_u) ** 2.6).clip(0.0) ** (1.0 / 2.6)
    rings = []
    for t in _PALM_T:
        width, dorsal, palmar = _palm_profile(t)
        y = np.where(shape > 0, dorsal, palmar) * shape * lift
        rings.append(np.stack((t * x_end, y, ring_u * width), axis=1))
    return np.stack(rings)


def _circle_angles(points: np.ndarray, centre: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Evenly spaced angles for a ring of N points, in the points' turning
    direction and aligned with their own angles about ``centre``."""
    rel = points - centre
    theta = np.arctan2(rel @ e2, rel @ e1)
    turn = np.sign(np.angle(np.exp(1j * np.diff(np.append(theta, theta[0])))).sum())
    even = turn * 2.0 * np.pi * np.arange(points.shape[0]) / points.shape[0]
    return even + np.angle(np.exp(1j * (theta - even)).mean())


def _digit_rings(digit: _Digit, base: np.ndarray, blend: float) -> np.ndarray:
    """Rings of a digit tube grown from its base ring (12, 3) -> (K, 12, 3), excluding
    the base and ending one tip radius before the tip. Over the first ``blend`` metres
    every vertex follows its own cubic Hermite path (leaving along the digit axis)
    from the base ring to an elliptic cross-section, so no ring folds or bunches."""
    d, e_dor = digit.direction, digit.dorsal
    e_lat = np.cross(d, e_dor)
    base_centre = base.mean(axis=0)
    s0 = float((base_centre - digit.first_joint) @ d)
    s_end = digit.length - digit.radii[1]
    phi = _circle_angles(base, base_centre, e_lat, e_dor)
    circle = 1.04 * np.cos(phi)[:, None] * e_lat + 0.96 * np.sin(phi)[:, None] * e_dor

    def section(s: float) -> np.ndarray:
        return digit.first_joint + s * d + digit.radius(s) * circle

    target = section(s0 + blend)
    tangent = np.linalg.norm(target - base, axis=1, keepdims=True) * d
    rings = []
    for s in np.linspace(s0, s_end, int(np.ceil((s_end - s0) / _RING_STEP)) + 1)[1:]:
        if s >= s0 + blend:
            rings.append(section(s))
            continue
        t = (s - s0) / blend
        h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
        rings.append(h00 * base + h10 * tangent + h01 * target + h11 * tangent)
    return np.stack(rings)


def _thumb(hole_points: np.ndarray) -> _Digit:
    base = hole_points.mean(axis=0)
    d = _THUMB_DIRECTION
    dorsal = _unit(_THUMB_DORSAL_HINT - (_THUMB_DORSAL_HINT @ d) * d)
    return _Digit("thumb", (13, 14, 15), base - _THUMB_BASE_DEPTH * d, d, dorsal, _THUMB_LENGTHS, _THUMB_RADII)


@dataclass(frozen=True)
class _HandMesh:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    part: np.ndarray  # (V,) 0 palm, 1..5 thumb, index, middle, ring, pinky
    tips: np.ndarray  # (5,) apex vertex of thumb, index, middle, ring, pinky
    digits: tuple[_Digit, ...]  # thumb, index, middle, ring, pinky


def _add_digit(builder: MeshBuilder, digit: _Digit, part_id: int, base_ids: np.ndarray, blend: float) -> int:
    """Grow a digit tube from a ring of existing points, round its tip; returns the apex point id."""
    rings = _digit_rings(digit, builder.points[base_ids], blend)
    tube = builder.extend_tube(base_ids, rings, part_id)
    middle = builder.close_with_dome(tube[-1], digit.direction, digit.radii[1], part_id)
    return int(middle[middle.size // 2])


def _hand_mesh() -> _HandMesh:
    builder = MeshBuilder()
    palm_ids = builder.add_points(_palm_rings(), PALM_PART)
    (r0, r1), (c0, c1) = _HOLE_RINGS, _HOLE_COLUMNS
    for j in range(palm_ids.shape[0] - 1):
        quads = ring_quads(palm_ids[j], palm_ids[j + 1])
        if r0 <= j < r1:
            quads = np.delete(quads, np.arange(c0, c1), axis=0)
        builder.add_faces(quads)
    builder.close_with_dome(palm_ids[0], np.array([-1.0, 0.0, 0.0]), 0.010, PALM_PART)
    # Thumb from the hole: [ring r0 cols c0..c1, col c1 up, ring r1 cols c1..c0, col c0 down].
    hole = np.concatenate(
        (
            palm_ids[r0, c0 : c1 + 1],
            palm_ids[r0 + 1 : r1, c1],
            palm_ids[r1, c0 : c1 + 1][::-1],
            palm_ids[r1 - 1 : r0 : -1, c0],
        )
    )
    thumb = _thumb(builder.points[hole])
    tips = [_add_digit(builder, thumb, 1, hole, blend=0.024)]
    # Fingers from the distal palm ring, split by three web points between the columns.
    distal = palm_ids[-1]
    n = _N_COL * 4
    top, right, bottom, left = distal[: n + 1], distal[n + 1], distal[n + 2 : 2 * n + 3][::-1], distal[-1]
    points = builder.points
    webs = [
        int(builder.add_points(0.5 * (points[top[c]] + points[bottom[c]]), PALM_PART)) for c in range(_N_COL, n, _N_COL)
    ]
    sides = [left, *webs, right]
    for k, finger in enumerate(_FINGERS):
        cols = slice(k * _N_COL, (k + 1) * _N_COL + 1)
        base = np.concatenate((top[cols], [sides[k + 1]], bottom[cols][::-1], [sides[k]]))
        tips.append(_add_digit(builder, finger, 2 + k, base, blend=0.012))
    vertices, faces, remap = builder.build()
    return _HandMesh(vertices, faces, builder.labels[remap >= 0], remap[np.array(tips)], (thumb, *_FINGERS))


def _joint_targets(digits: tuple[_Digit, ...]) -> np.ndarray:
    """(16, 3) designed rest joints: wrist, then each digit's three joints."""
    joints = np.zeros((NUM_JOINTS, 3))
    joints[0] = (0.006, 0.0, 0.0)
    for digit in digits:
        joints[list(digit.joints)] = digit.joint_positions[:3]
    return joints


def _bones(digits: tuple[_Digit, ...]) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """(joint, start, end, bone radius) segments: carpals and metacarpals belong to the
    wrist, each phalanx to the joint at its base; phalanges sit slightly dorsal."""
    bones = [(0, np.array([0.004, 0.0, -0.017]), np.array([0.004, 0.0, 0.017]), 0.009)]
    for digit in digits:
        pos = digit.joint_positions
        pos[3] = pos[3] - _TIP_BONE_GAP * digit.direction
        shift = 0.15 * digit.radii[0] * digit.dorsal
        if digit.name != "thumb":
            bones.append((0, np.array([0.014, 0.0, 0.7 * pos[0, 2]]), pos[0], 0.0045))
        for k, joint in enumerate(digit.joints):
            radius = (0.48 if k < 2 else 0.38) * float(digit.radius((k + 0.5) * digit.length / 3.0))
            bones.append((joint, pos[k] + shift, pos[k + 1] + shift, radius))
    return bones


def _skinning(
    vertices: np.ndarray,
    faces: np.ndarray,
    part: np.ndarray,
    digits: tuple[_Digit, ...],
    bones: list[tuple[int, np.ndarray, np.ndarray, float]],
) -> np.ndarray:
    """(V, 16) weights: soft-min over bone distances among the allowed joints
    (palm: wrist and each digit's first joint; digit: wrist and its own joints)."""
    dist = np.full((vertices.shape[0], NUM_JOINTS), np.inf)
    for joint, a, b, _ in bones:
        dist[:, joint] = np.minimum(dist[:, joint], segment_distance(vertices, a, b))
    allowed = np.zeros_like(dist, dtype=bool)
    allowed[:, 0] = True
    allowed[np.ix_(part == PALM_PART, [d.joints[0] for d in digits])] = True
    for k, digit in enumerate(digits):
        allowed[np.ix_(part == 1 + k, list(digit.joints))] = True
    return smooth_weights(softmin_weights(dist, allowed, _TAU), faces, allowed, _SMOOTH_ITERS)


def _inner_distance(vertices: np.ndarray, bones: list[tuple[int, np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """(V,) skin-to-bone depth: distance to the nearest bone surface, clipped at 0."""
    depth = np.min([segment_distance(vertices, a, b) - r for _, a, b, r in bones], axis=0)
    return np.clip(depth, 0.0, None)


def _digit_coords(vertices: np.ndarray, digit: _Digit) -> tuple[np.ndarray, np.ndarray]:
    """Arc length along the digit axis from its first joint (V,) and the radial offset (V, 3)."""
    rel = vertices - digit.first_joint
    s = rel @ digit.direction
    return s, rel - s[:, None] * digit.direction


def _ownership(weights: np.ndarray, digits: tuple[_Digit, ...]) -> np.ndarray:
    """(5, V): how much each vertex follows each digit (sum of its joints' weights)."""
    return np.stack([weights[:, list(d.joints)].sum(axis=1) for d in digits])


def _posedirs(vertices: np.ndarray, weights: np.ndarray, digits: tuple[_Digit, ...]) -> np.ndarray:
    """(V, 3, 135) knuckle correctives (see the module docstring)."""
    posedirs = np.zeros((vertices.shape[0], 3, 9 * (NUM_JOINTS - 1)))
    own = _ownership(weights, digits)
    for k, digit in enumerate(digits):
        for joint, s_joint in zip(digit.joints, np.concatenate(([0.0], np.cumsum(digit.lengths)[:2]))):
            s, radial = _digit_coords(vertices, digit)
            r = float(digit.radius(s_joint))
            rho = radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
            falloff = own[k] * np.exp(-0.5 * ((s - s_joint) / (0.7 * r)) ** 2)
            cos_dorsal = rho @ digit.dorsal
            dorsal = falloff * np.clip(cos_dorsal, 0.0, None) ** 2
            palmar = falloff * np.clip(-cos_dorsal, 0.0, None) ** 2
            knuckle = 0.20 * r * dorsal[:, None] * rho
            crease_stretch = 0.5 * (palmar * (s - s_joint))[:, None] * digit.direction
            palmar_bulge = 0.12 * r * palmar[:, None] * rho
            block = slice(9 * (joint - 1), 9 * joint)
            posedirs[:, :, block] = axis_corrective(knuckle + crease_stretch, palmar_bulge, digit.flex_axis)
    return posedirs


def _shapedirs(vertices: np.ndarray, weights: np.ndarray, digits: tuple[_Digit, ...]) -> np.ndarray:
    """(V, 3, 10) shape directions (see the module docstring)."""
    own = _ownership(weights, digits)
    palm = 1.0 - own.sum(axis=0)
    coords = [_digit_coords(vertices, d) for d in digits]
    x_hat, y_hat, z_hat = np.eye(3)
    anchor = np.stack([d.first_joint for d in digits])  # (5, 3)

    def digit_sum(fn: Callable[[int], np.ndarray], which: range) -> np.ndarray:
        return sum(own[k][:, None] * fn(k) for k in which)

    def lengthen(k: int) -> np.ndarray:
        return np.clip(coords[k][0], 0.0, None)[:, None] * digits[k].direction

    def thicken(k: int) -> np.ndarray:
        return coords[k][1]

    def fuller_tip(k: int) -> np.ndarray:
        return (np.clip(coords[k][0], 0.0, None) / digits[k].length)[:, None] ** 2 * coords[k][1]

    thumb, fingers, all_digits = range(1), range(1, 5), range(5)
    x, y, z = vertices.T
    dirs = [
        0.07 * (vertices - np.array([0.006, 0.0, 0.0])),
        0.10 * digit_sum(lengthen, fingers),
        0.10 * (palm * z + own.T @ anchor[:, 2])[:, None] * z_hat,
        0.10 * digit_sum(thicken, fingers),
        0.12 * (palm * y)[:, None] * y_hat,
        0.08 * (palm * x + own.T @ anchor[:, 0])[:, None] * x_hat,
        0.10 * digit_sum(lengthen, thumb),
        0.12 * digit_sum(thicken, thumb),
        0.15 * digit_sum(fuller_tip, all_digits),
        -0.004 * (palm * smoothstep(0.0, -0.01, y))[:, None] * y_hat,
    ]
    return np.stack(dirs, axis=2)


def _pose_synergies(digits: tuple[_Digit, ...]) -> tuple[np.ndarray, np.ndarray]:
    """-> hands_components (45, 45) orthonormal rows led by hand synergies, hands_mean (45,)."""

    def synergy(per_digit: Mapping[str, tuple[float, float, float]], axis: str = "flex") -> np.ndarray:
        pose = np.zeros((NUM_JOINTS, 3))
        for digit in digits:
            a = digit.flex_axis if axis == "flex" else digit.dorsal
            for joint, angle in zip(digit.joints, per_digit.get(digit.name, (0.0, 0.0, 0.0))):
                pose[joint] = angle * a
        return pose[1:].reshape(-1)

    curl = {name: (0.7, 1.0, 0.6) for name in DIGIT_NAMES[1:]} | {"thumb": (0.3, 0.4, 0.5)}
    spread = {"index": (-0.25, 0, 0), "ring": (0.15, 0, 0), "pinky": (0.3, 0, 0), "thumb": (-0.3, 0, 0)}
    leading = np.stack(
        [
            synergy(curl),
            synergy(spread, axis="dorsal"),
            synergy({"thumb": (0.6, 0.3, 0.2)}) + synergy({"thumb": (0.5, 0, 0)}, axis="dorsal"),
            synergy({"thumb": (0.4, 0.4, 0.4), "index": (0.6, 0.7, 0.5)}),
            synergy({name: (1.2, 1.4, 0.9) for name in ("middle", "ring", "pinky")}),
        ]
    )
    leading /= np.linalg.norm(leading, axis=1, keepdims=True)
    return orthonormal_completion(leading), 0.15 * synergy(curl)


def _part_labels(vertices: np.ndarray, part: np.ndarray, digits: tuple[_Digit, ...]) -> dict[str, np.ndarray]:
    labels = {"palm": np.flatnonzero(part == PALM_PART)}
    for k, digit in enumerate(digits):
        labels[digit.name] = np.flatnonzero(part == 1 + k)
    labels["palmar"] = np.flatnonzero((part == PALM_PART) & (vertices[:, 1] < -0.004) & (vertices[:, 0] > 0.0))
    near_tip = np.zeros(vertices.shape[0], dtype=bool)
    for k, digit in enumerate(digits):
        s, _ = _digit_coords(vertices, digit)
        near_tip |= (part == 1 + k) & (s > digit.length - 0.012)
    labels["fingertips"] = np.flatnonzero(near_tip)
    return labels


def build_hand() -> TemplateModel:
    """Build the procedural right hand (see the module docstring)."""
    mesh = _hand_mesh()
    digits = mesh.digits
    joints = _joint_targets(digits)
    sigmas = np.array([0.015] + [0.008] * 12 + [0.012, 0.008, 0.008])
    sigmas[[d.joints[0] for d in digits[1:]]] = 0.008
    regressor = joint_regressor(mesh.vertices, joints, sigmas)
    bones = _bones(digits)
    weights = _skinning(mesh.vertices, mesh.faces, mesh.part, digits, bones)
    components, mean = _pose_synergies(digits)
    return TemplateModel(
        name="mano",
        v_template=mesh.vertices,
        shapedirs=_shapedirs(mesh.vertices, weights, digits),
        posedirs=_posedirs(mesh.vertices, weights, digits),
        J_regressor=regressor,
        weights=weights,
        kintree_table=np.stack((np.array(MANO_PARENTS), np.arange(NUM_JOINTS))),
        faces=mesh.faces,
        hands_components=components,
        hands_mean=mean,
        inner_distance=_inner_distance(mesh.vertices, bones),
        part_labels=_part_labels(mesh.vertices, mesh.part, digits),
        tip_vertex_ids=mesh.tips,
    )
