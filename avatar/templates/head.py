"""A procedural head and neck with the FLAME layout (5 joints, shape + expression).

Axes (metres): origin at the skull centre, y up, the face looks along +z, the
subject's left is +x. Chin-to-crown ~23 cm, width ~15.5 cm, neck down to
y ~ -0.21.

Surface: a star-shaped radial surface ``p = r(u) u`` over a subdivided
icosphere (level 4, 2562 vertices) whose directions are warped toward the face
(denser where the lips, nose and eyes are). ``r(u)`` is a smooth maximum of the
exit distances of a cranium ellipsoid, a face / jaw ellipsoid and a neck
capsule, plus direction-space Gaussian bumps (nose, cheeks, lips and a mouth
groove, chin, brows, eye sockets and eyeballs). Being star-shaped it is
watertight and fold-free by construction.

Rig: joints 0 global (neck base), 1 neck (skull base), 2 jaw, 3 left eye,
4 right eye, parents [-1, 0, 1, 1, 1]. The jaw drives the lower lip, chin,
lower cheeks and the floor of the mouth with a sharp boundary at the mouth
groove, so opening the jaw opens the lips; the eye joints drive the eyeball
caps; the lower neck blends to the global joint.

Soft tissue: ``inner_distance`` is the distance from each skin vertex to a
rigid inner surface (a shrunken cranium / maxilla-mandible union with nasal
bone, brow ridges, cheekbones, chin, orbits and a hollow under the cheeks, plus
the cervical spine): ~6 mm on the forehead and scalp, 5-7 mm on the nose bridge,
~9 mm at the chin, 1.2-2.2 cm in the cheeks, 2-4 cm in the neck.

Shape space: identity first, then expression.

* Columns 0-9, the designed identity (the synthetic subjects use only these):
  size, face width, face length, nose size, cheek fullness, jaw width, chin
  protrusion, lip thickness, brow ridge, eye depth.
* Columns 10-12, global proportions a designed head lacks: head width (whole
  head), face depth (the face's protrusion), upper-face height.
* Columns 13-216, landmark-region offsets, so that the head can take on the
  proportions of heads it was not built from: for each of the 68 landmarks and
  each axis x, y, z, a smooth field (a Gaussian kernel of ``_REGION_SIGMA`` in
  the Euclidean distance to the rest landmarks, regularised interpolation)
  that moves that landmark by ~1 cm per unit coefficient and its neighbours by
  little. Their columns are
  ordered landmark-major (landmark k, axis a at 13 + 3 k + a). Their
  ``shape_roughness`` is the squared difference of each landmark's offset from
  the mean of its ``_REGION_NEIGHBOURS`` nearest landmarks' (a graph Laplacian
  prior): fitting prefers smooth corrections, which a different head needs and
  keypoint noise does not make. ``num_core_shape`` marks the designed columns: a
  fit to detections with systematic offsets (MediaPipe's) keeps to them, because
  the landmark-region offsets would follow the detector's bias.
* The last 10 columns, expression: smile, mouth stretch, pucker, cheek puff,
  brow raise, frown, blink, mouth sideways, lip press, nose wrinkle.
Pose correctives: neck flexion bulges the front of the neck, jaw opening thins
the lower lip and lifts the floor of the mouth, eye pitch moves the upper lids.

Landmarks: 68 points in iBUG order (jaw contour 0-16, brows 17-26, nose 27-35,
eyes 36-47, mouth 48-67; the subject's right side first), each embedded where
a ray from the origin through its design direction meets the surface.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from avatar.templates.landmarks import embed_directions
from avatar.templates.model import TemplateModel
from avatar.templates.rigging import axis_corrective, joint_regressor, smoothstep

NUM_JOINTS = 5
FLAME_PARENTS = (-1, 0, 1, 1, 1)
NUM_DESIGNED_SHAPE = 10
NUM_GLOBAL_SHAPE = 3
NUM_LANDMARKS = 68
NUM_SHAPE = NUM_DESIGNED_SHAPE + NUM_GLOBAL_SHAPE + 3 * NUM_LANDMARKS
NUM_EXPRESSION = 10
_REGION_SIGMA = 0.015  # m: reach of a landmark-region offset field
_REGION_AMPLITUDE = 0.01  # m: landmark displacement per unit coefficient
_REGION_RIDGE = 0.05  # Tikhonov term of the interpolation (nearby landmarks share their fields)
_REGION_NEIGHBOURS = 4

_FOCUS = np.array([0.0, -0.25, 1.0]) / np.linalg.norm([0.0, -0.25, 1.0])
_WARP = 0.6  # direction warp strength: mesh ~2.5x denser at the face than at the back
_EYE = (0.38, 0.335)  # yaw, pitch of the left eye (right eye mirrored)
_MOUTH_PITCH = -0.555
_MOUTH_HALF_YAW = 0.26

# (amplitude m, yaw, pitch, sigma_yaw, sigma_pitch, yaw power, mirrored)
_Bump = tuple[float, float, float, float, float, int, bool]
_SKIN: dict[str, _Bump] = {
    "nose_ridge": (0.012, 0.0, 0.08, 0.07, 0.20, 2, False),
    "nose_tip": (0.016, 0.0, -0.13, 0.085, 0.075, 2, False),
    "nose_wing": (0.006, 0.16, -0.17, 0.06, 0.05, 2, True),
    "eye_socket": (-0.010, _EYE[0], _EYE[1], 0.17, 0.11, 2, True),
    "eyeball": (0.005, _EYE[0], _EYE[1], 0.075, 0.05, 2, True),
    "brow": (0.006, 0.38, 0.52, 0.22, 0.06, 2, True),
    "cheekbone": (0.005, 0.62, 0.12, 0.14, 0.10, 2, True),
    "cheek": (0.009, 0.52, -0.20, 0.20, 0.17, 2, True),
    "upper_lip": (0.007, 0.0, -0.50, 0.22, 0.045, 4, False),
    "lower_lip": (0.008, 0.0, -0.615, 0.19, 0.05, 4, False),
    "mouth_groove": (-0.008, 0.0, _MOUTH_PITCH, 0.25, 0.022, 4, False),
    "chin": (0.008, 0.0, -0.88, 0.20, 0.12, 2, False),
    "labiomental": (-0.003, 0.0, -0.72, 0.15, 0.04, 2, False),
}
_SKULL: dict[str, _Bump] = {
    "nasal_bone": (0.010, 0.0, 0.20, 0.06, 0.10, 2, False),
    "brow": _SKIN["brow"],
    "cheekbone": _SKIN["cheekbone"],
    "chin": (0.010, 0.0, -0.90, 0.18, 0.12, 2, False),
    "orbit": (-0.022, _EYE[0], _EYE[1], 0.15, 0.10, 2, True),
    "buccal_hollow": (-0.006, 0.50, -0.28, 0.16, 0.12, 2, True),  # no bone under the cheeks
}
# (centre, semi-axes) of the convex primitives; all contain the origin.
_CRANIUM = (np.array([0.0, 0.012, -0.010]), np.array([0.0765, 0.098, 0.100]))
_FACE = (np.array([0.0, -0.045, 0.015]), np.array([0.062, 0.088, 0.078]))
_NECK = (np.array([0.0, -0.02, -0.018]), np.array([0.0, -0.16, -0.025]), 0.054)  # segment ends, radius
_SCALP = np.array([0.006, 0.006, 0.006])  # cranium soft tissue per axis
_FACE_TISSUE = np.array([0.016, 0.006, 0.012])  # maxilla / mandible soft tissue per axis
_SPINE = (np.array([0.0, -0.03, -0.035]), np.array([0.0, -0.18, -0.035]), 0.018)
_SMOOTH_MAX = 0.012


def _total(terms: Iterable[np.ndarray]) -> np.ndarray:
    """Elementwise sum (the built-in ``sum``) of a non-empty iterable of arrays."""
    total = sum(terms)
    if not isinstance(total, np.ndarray):
        raise ValueError("_total needs at least one array")
    return total


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _warped_sphere(subdivisions: int, warp: float) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere directions (N, 3) pulled toward ``_FOCUS`` (polar angle a -> a - warp sin a), faces (F, 3)."""
    sphere = trimesh.creation.icosphere(subdivisions)
    u = np.asarray(sphere.vertices, dtype=np.float64)
    cos_a = np.clip(u @ _FOCUS, -1.0, 1.0)
    alpha = np.arccos(cos_a)
    side = u - cos_a[:, None] * _FOCUS
    norm = np.linalg.norm(side, axis=1, keepdims=True)
    side = np.where(norm > 1e-12, side / np.maximum(norm, 1e-12), 0.0)
    warped = alpha - warp * np.sin(alpha)
    return np.cos(warped)[:, None] * _FOCUS + np.sin(warped)[:, None] * side, np.asarray(sphere.faces, dtype=np.int64)


def _yaw_pitch(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.arctan2(u[:, 0], u[:, 2]), np.arctan2(u[:, 1], np.hypot(u[:, 0], u[:, 2]))


def _patch(u: np.ndarray, yaw0: float, pitch0: float, s_yaw: float, s_pitch: float, power: int = 2) -> np.ndarray:
    """(N,) direction-space bump in [0, 1]: Gaussian in pitch, power-``power`` in yaw."""
    yaw, pitch = _yaw_pitch(u)
    d_yaw = np.angle(np.exp(1j * (yaw - yaw0)))
    return np.exp(-0.5 * np.abs(d_yaw / s_yaw) ** power - 0.5 * ((pitch - pitch0) / s_pitch) ** 2)


def _bump(u: np.ndarray, spec: _Bump, side: float | None = None) -> np.ndarray:
    """Radial bump (N,) of one feature; mirrored features sum both sides unless ``side`` (+1 left, -1 right)."""
    amp, yaw, pitch, s_yaw, s_pitch, power, mirrored = spec
    sides = ([1.0, -1.0] if side is None else [side]) if mirrored else [1.0]
    return amp * _total(_patch(u, s * yaw, pitch, s_yaw, s_pitch, power) for s in sides)


def _ellipsoid_exit(u: np.ndarray, centre: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Distance (N,) along rays from the origin to the surface of an ellipsoid containing it."""
    a = ((u / axes) ** 2).sum(axis=1)
    b = -2.0 * (u * centre / axes**2).sum(axis=1)
    c = float(((centre / axes) ** 2).sum() - 1.0)
    return (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def _capsule_exit(u: np.ndarray, start: np.ndarray, end: np.ndarray, radius: float) -> np.ndarray:
    """Distance (N,) along rays from the origin to the surface of a capsule containing it (bisection)."""
    lo, hi = np.zeros(u.shape[0]), np.full(u.shape[0], 1.0)
    ab = end - start
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        p = mid[:, None] * u
        t = np.clip(((p - start) @ ab) / (ab @ ab), 0.0, 1.0)
        inside = np.linalg.norm(p - start - t[:, None] * ab, axis=1) < radius
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def _smooth_max(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(k - np.abs(a - b), 0.0, None) / k
    return np.maximum(a, b) + h * h * k / 4.0


def _skin_radius(u: np.ndarray) -> np.ndarray:
    base = _smooth_max(_ellipsoid_exit(u, *_CRANIUM), _ellipsoid_exit(u, *_FACE), _SMOOTH_MAX)
    base = _smooth_max(base, _capsule_exit(u, *_NECK), _SMOOTH_MAX)
    return base + sum(_bump(u, spec) for spec in _SKIN.values())


def _skull_radius(u: np.ndarray) -> np.ndarray:
    cranium = _ellipsoid_exit(u, _CRANIUM[0], _CRANIUM[1] - _SCALP)
    face = _ellipsoid_exit(u, _FACE[0], _FACE[1] - _FACE_TISSUE)
    return _smooth_max(cranium, face, _SMOOTH_MAX) + sum(_bump(u, spec) for spec in _SKULL.values())


def _inner_distance(vertices: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(V,) distance from each skin vertex to the skull (dense radial samples) or the
    cervical spine (capsule), zero where the skin would lie inside the bone."""
    dirs, _ = _warped_sphere(5, 0.0)
    tree = cKDTree(_skull_radius(dirs)[:, None] * dirs)
    to_skull, _ = tree.query(vertices)
    start, end, radius = _SPINE
    ab = end - start
    t = np.clip(((vertices - start) @ ab) / (ab @ ab), 0.0, 1.0)
    to_spine = np.linalg.norm(vertices - start - t[:, None] * ab, axis=1) - radius
    inside = np.linalg.norm(vertices, axis=1) < _skull_radius(u)
    return np.where(inside, 0.0, np.clip(np.minimum(to_skull, to_spine), 0.0, None))


class _Regions:
    """Smooth direction-space masks (N,) of the rest head, shared by rig, blend shapes and labels."""

    def __init__(self, u: np.ndarray, vertices: np.ndarray) -> None:
        self.u, self.v = u, vertices
        self.yaw, self.pitch = _yaw_pitch(u)

    def patch(self, yaw: float, pitch: float, s_yaw: float, s_pitch: float, power: int = 2) -> np.ndarray:
        return _patch(self.u, yaw, pitch, s_yaw, s_pitch, power)

    def jaw(self) -> np.ndarray:
        """Jaw weight: 1 below the mouth groove and along the lower face, 0 above,
        fading behind the jaw angle and down the neck."""
        side = smoothstep(_MOUTH_HALF_YAW, 1.25, np.abs(self.yaw))
        boundary = _MOUTH_PITCH + 0.45 * side
        width = 0.02 + 0.16 * side
        below = smoothstep(boundary + width, boundary - width, self.pitch)
        return below * (1.0 - smoothstep(1.2, 1.5, np.abs(self.yaw))) * (1.0 - smoothstep(-1.0, -1.3, self.pitch))

    def eyeball(self, side: float) -> np.ndarray:
        return self.patch(side * _EYE[0], _EYE[1], 0.06, 0.04, power=4) ** 2

    def eyelid(self, side: float) -> np.ndarray:
        return self.patch(side * _EYE[0], _EYE[1] + 0.045, 0.12, 0.03)

    def lips(self) -> np.ndarray:
        return self.patch(0.0, _MOUTH_PITCH, 0.25, 0.08, power=4)

    def lip(self, upper: bool) -> np.ndarray:
        return self.patch(0.0, _MOUTH_PITCH + (0.05 if upper else -0.06), 0.22, 0.045, power=4)

    def corner(self, side: float) -> np.ndarray:
        return self.patch(side * _MOUTH_HALF_YAW, _MOUTH_PITCH, 0.08, 0.07)

    def cheek(self, side: float) -> np.ndarray:
        return self.patch(side * 0.5, -0.25, 0.18, 0.16)

    def brow(self) -> np.ndarray:
        return _total(self.patch(s * 0.36, 0.52, 0.2, 0.08) for s in (1.0, -1.0))

    def front(self) -> np.ndarray:
        return smoothstep(-0.3, 0.5, self.u[:, 2])

    def under_chin(self) -> np.ndarray:
        return self.patch(0.0, -1.05, 0.45, 0.12)

    def neck_front(self) -> np.ndarray:
        return smoothstep(-0.10, -0.14, self.v[:, 1]) * smoothstep(-0.2, 0.6, self.u[:, 2])


def _joint_targets(u_eye: np.ndarray, r_eye: np.ndarray) -> np.ndarray:
    """(5, 3) designed rest joints; eyes from their directions (2, 3) and skin radii (2,)."""
    joints = np.array([[0.0, -0.160, -0.022], [0.0, -0.045, -0.025], [0.0, -0.028, 0.000], [0, 0, 0], [0, 0, 0.0]])
    joints[3:] = (r_eye - 0.012)[:, None] * u_eye  # eyeball centres 12 mm behind the cornea
    return joints


def _skinning(reg: _Regions) -> np.ndarray:
    """(V, 5) weights: jaw, eyes and lower neck carved out of the neck joint's region."""
    w = np.zeros((reg.u.shape[0], NUM_JOINTS))
    w[:, 2] = reg.jaw()
    w[:, 3], w[:, 4] = reg.eyeball(1.0), reg.eyeball(-1.0)
    w[:, 0] = smoothstep(-0.11, -0.17, reg.v[:, 1]) * (1.0 - w[:, 2])
    w[w < 1e-6] = 0.0
    w[:, 1] = np.clip(1.0 - w.sum(axis=1), 0.0, None)
    return w / w.sum(axis=1, keepdims=True)


def _landmark_region_fields(vertices: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(V, 3, 3 L) fields, landmark-major: field (k, a) moves landmark k (L, 3 rest positions)
    by ~``_REGION_AMPLITUDE`` along axis a, decaying with distance as a Gaussian of
    ``_REGION_SIGMA``. Regularised interpolation ``K_vl (K_ll + r I)^-1`` keeps the
    fields of landmarks a few millimetres apart (inner and outer lips) from cancelling."""

    def kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        return np.exp(-0.5 * d2 / _REGION_SIGMA**2)

    L = landmarks.shape[0]
    weights = kernel(vertices, landmarks) @ np.linalg.inv(kernel(landmarks, landmarks) + _REGION_RIDGE * np.eye(L))
    weights *= 1.0 + _REGION_RIDGE  # an isolated landmark moves by exactly the amplitude
    fields = _REGION_AMPLITUDE * weights[:, None, :, None] * np.eye(3)[None, :, None, :]  # (V, 3, L, 3)
    return fields.reshape(vertices.shape[0], 3, 3 * L)


def _landmark_region_roughness(landmarks: np.ndarray) -> np.ndarray:
    """(NUM_SHAPE, NUM_SHAPE) ``D^T D`` over the identity columns, ``D`` = identity minus the mean
    over each landmark's ``_REGION_NEIGHBOURS`` nearest landmarks (L, 3 rest positions), per axis, on
    the landmark-region columns; zero on the designed and global ones."""
    L = landmarks.shape[0]
    distance = np.linalg.norm(landmarks[:, None] - landmarks[None], axis=-1)
    neighbours = np.argsort(distance, axis=1)[:, 1 : _REGION_NEIGHBOURS + 1]
    difference = np.eye(L)
    np.put_along_axis(difference, neighbours, -1.0 / _REGION_NEIGHBOURS, axis=1)
    per_axis = np.kron(difference, np.eye(3))  # landmark-major, axis-minor like the columns
    roughness = np.zeros((NUM_SHAPE, NUM_SHAPE))
    start = NUM_DESIGNED_SHAPE + NUM_GLOBAL_SHAPE
    roughness[start:, start:] = per_axis.T @ per_axis
    return roughness


def _shapedirs(reg: _Regions, landmarks: np.ndarray) -> np.ndarray:
    """(V, 3, NUM_SHAPE + NUM_EXPRESSION): identity then expression displacement fields
    (see module docstring); ``landmarks`` (68, 3) are the rest landmark positions."""
    v, u = reg.v, reg.u
    x_hat, y_hat, _ = np.eye(3)

    def field(mask: np.ndarray, vector: np.ndarray) -> np.ndarray:
        return mask[:, None] * vector

    def radial(spec_names: tuple[str, ...], table: dict[str, _Bump], gain: float) -> np.ndarray:
        return gain * _total(_bump(u, table[n]) for n in spec_names)[:, None] * u

    sides = (1.0, -1.0)
    lower_face = reg.front() * smoothstep(0.0, -0.06, v[:, 1])
    identity = [  # NUM_DESIGNED_SHAPE fields
        0.05 * v,
        field(0.08 * reg.front() * v[:, 0], x_hat),
        field(0.10 * lower_face * v[:, 1], y_hat),
        radial(("nose_ridge", "nose_tip", "nose_wing"), _SKIN, 0.3),
        radial(("cheek",), _SKIN, 0.5),
        field(0.10 * smoothstep(-0.02, -0.08, v[:, 1]) * (1.0 - smoothstep(-0.14, -0.17, v[:, 1])) * v[:, 0], x_hat),
        field(reg.patch(0.0, -0.85, 0.25, 0.15), np.array([0.0, -0.003, 0.005])),
        radial(("upper_lip", "lower_lip"), _SKIN, 0.35),
        radial(("brow",), _SKIN, 0.6),
        radial(("eye_socket",), _SKIN, 0.4),
    ]
    global_proportions = [  # NUM_GLOBAL_SHAPE fields
        field(0.08 * v[:, 0], x_hat),
        field(0.10 * reg.front() * v[:, 2], np.array([0.0, 0.0, 1.0])),
        field(0.10 * reg.front() * smoothstep(-0.02, 0.04, v[:, 1]) * v[:, 1], y_hat),
    ]
    expression = [  # NUM_EXPRESSION fields
        sum(
            field(reg.corner(s), np.array([s * 0.006, 0.005, -0.002]))
            + field(reg.cheek(s), np.array([0.0, 0.003, 0.002]))
            for s in sides
        ),
        field(reg.lip(upper=False) + 0.6 * reg.patch(0.0, -0.85, 0.3, 0.2), -0.006 * y_hat)
        + field(reg.lip(upper=True), 0.002 * y_hat),
        field(reg.lips(), np.array([0.0, 0.0, 0.007])) + field(-0.25 * reg.lips() * v[:, 0], x_hat),
        sum(0.008 * reg.cheek(s)[:, None] * u for s in sides),
        field(reg.brow() + 0.5 * reg.patch(0.0, 0.75, 0.5, 0.15), 0.005 * y_hat),
        field(reg.brow(), np.array([0.0, -0.004, 0.001])) + field(-0.15 * reg.brow() * v[:, 0], x_hat),
        sum(field(reg.eyelid(s), np.array([0.0, -0.006, 0.001])) for s in sides),
        field(reg.lips(), 0.006 * x_hat),
        -0.004 * reg.lips()[:, None] * u,
        field(sum(reg.patch(s * 0.15, -0.05, 0.08, 0.12) for s in sides) + 0.5 * reg.lip(upper=True), 0.004 * y_hat),
    ]
    return np.concatenate(
        (
            np.stack(identity + global_proportions, axis=2),
            _landmark_region_fields(v, landmarks),
            np.stack(expression, axis=2),
        ),
        axis=2,
    )


def _posedirs(reg: _Regions) -> np.ndarray:
    """(V, 3, 36) correctives for the neck, jaw and eye joints (see module docstring)."""
    zero = np.zeros_like(reg.v)
    x_axis = np.array([1.0, 0.0, 0.0])
    neck = axis_corrective(zero, 0.010 * reg.neck_front()[:, None] * reg.u, x_axis)
    jaw_sym = reg.lip(upper=False)[:, None] * np.array([0.0, 0.0, -0.02]) + reg.under_chin()[:, None] * np.array(
        [0.0, 0.012, 0.0]
    )
    jaw = axis_corrective(jaw_sym, reg.lip(upper=True)[:, None] * np.array([0.0, -0.006, 0.0]), x_axis)
    eyes = [axis_corrective(zero, reg.eyelid(s)[:, None] * np.array([0.0, -0.008, 0.0]), x_axis) for s in (1.0, -1.0)]
    return np.concatenate([neck, jaw, *eyes], axis=2)


def _part_labels(reg: _Regions, weights: np.ndarray) -> dict[str, np.ndarray]:
    v, pitch = reg.v, reg.pitch
    face = (reg.u[:, 2] > 0.35) & (pitch > -1.0) & (pitch < 0.75)
    masks: dict[str, np.ndarray] = {
        "face": face,
        "lips": reg.lips() > 0.3,
        "nose": _total(_bump(reg.u, _SKIN[n]) for n in ("nose_ridge", "nose_tip", "nose_wing")) > 0.004,
        "cheek_left": reg.cheek(1.0) > 0.35,
        "cheek_right": reg.cheek(-1.0) > 0.35,
        "eye_left": reg.patch(_EYE[0], _EYE[1], 0.13, 0.08) > 0.4,
        "eye_right": reg.patch(-_EYE[0], _EYE[1], 0.13, 0.08) > 0.4,
        "forehead": face & (pitch > 0.6),
        "chin": reg.patch(0.0, -0.88, 0.22, 0.13) > 0.4,
        "jaw": weights[:, 2] > 0.5,
        "neck": (v[:, 1] < -0.115) & (weights[:, 2] < 0.3),
        "scalp": (reg.u[:, 2] < 0.35) & (v[:, 1] > -0.02),
    }
    return {name: np.flatnonzero(mask) for name, mask in masks.items()}


def _landmark_directions() -> np.ndarray:
    """(68, 3) iBUG-68 landmark directions (jaw 0-16, brows 17-26, nose 27-35,
    eyes 36-47, mouth 48-67); the subject's right (-x) comes first."""
    psi = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 17)
    jaw = np.stack((1.2 * np.sin(psi), -0.05 - 0.85 * np.cos(psi)), axis=1)
    brow_right = np.stack((np.linspace(-0.64, -0.10, 5), [0.46, 0.52, 0.545, 0.54, 0.52]), axis=1)
    brow_left = brow_right[::-1] * [-1.0, 1.0]
    nose = [(0.0, 0.30), (0.0, 0.16), (0.0, 0.02), (0.0, -0.13)] + [
        (y, -0.25) for y in (-0.13, -0.065, 0.0, 0.065, 0.13)
    ]
    ey, ep = _EYE
    eye_right = [
        (-ey - 0.14, ep),
        (-ey - 0.05, ep + 0.045),
        (-ey + 0.05, ep + 0.045),
        (-ey + 0.14, ep),
        (-ey + 0.05, ep - 0.04),
        (-ey - 0.05, ep - 0.04),
    ]
    eye_left = [
        (ey - 0.14, ep),
        (ey - 0.05, ep + 0.045),
        (ey + 0.05, ep + 0.045),
        (ey + 0.14, ep),
        (ey + 0.05, ep - 0.04),
        (ey - 0.05, ep - 0.04),
    ]
    m, c = _MOUTH_PITCH, _MOUTH_HALF_YAW
    outer = [
        (-c, m),
        (-0.16, m + 0.04),
        (-0.06, m + 0.06),
        (0.0, m + 0.055),
        (0.06, m + 0.06),
        (0.16, m + 0.04),
        (c, m),
        (0.16, m - 0.045),
        (0.07, m - 0.07),
        (0.0, m - 0.075),
        (-0.07, m - 0.07),
        (-0.16, m - 0.045),
    ]
    inner = [
        (-0.22, m),
        (-0.08, m + 0.01),
        (0.0, m + 0.01),
        (0.08, m + 0.01),
        (0.22, m),
        (0.08, m - 0.01),
        (0.0, m - 0.01),
        (-0.08, m - 0.01),
    ]
    yaw_pitch = np.concatenate(
        [
            jaw,
            brow_right,
            brow_left,
            np.array(nose),
            np.array(eye_right),
            np.array(eye_left),
            np.array(outer),
            np.array(inner),
        ]
    )
    yaw, pitch = yaw_pitch.T
    return np.stack((np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)), axis=1)


def build_head() -> TemplateModel:
    """Build the procedural head (see the module docstring)."""
    u, faces = _warped_sphere(4, _WARP)
    vertices = _skin_radius(u)[:, None] * u
    reg = _Regions(u, vertices)
    u_eye = _unit(
        np.array(
            [
                [np.cos(_EYE[1]) * np.sin(s * _EYE[0]), np.sin(_EYE[1]), np.cos(_EYE[1]) * np.cos(_EYE[0])]
                for s in (1.0, -1.0)
            ]
        )
    )
    joints = _joint_targets(u_eye, _skin_radius(u_eye))
    regressor = joint_regressor(vertices, joints, np.array([0.04, 0.05, 0.05, 0.03, 0.03]))
    weights = _skinning(reg)
    lmk_faces, lmk_bary = embed_directions(vertices, faces, np.zeros(3), _landmark_directions())
    landmarks = np.einsum("lk,lkc->lc", lmk_bary, vertices[faces[lmk_faces]])
    return TemplateModel(
        name="flame",
        v_template=vertices,
        shapedirs=_shapedirs(reg, landmarks),
        posedirs=_posedirs(reg),
        J_regressor=regressor,
        weights=weights,
        kintree_table=np.stack((np.array(FLAME_PARENTS), np.arange(NUM_JOINTS))),
        faces=faces,
        inner_distance=_inner_distance(vertices, u),
        num_shape=NUM_SHAPE,
        part_labels=_part_labels(reg, weights),
        landmark_faces=lmk_faces,
        landmark_bary=lmk_bary,
        shape_roughness=_landmark_region_roughness(landmarks),
        num_core_shape=NUM_DESIGNED_SHAPE,
    )
