"""The browser viewer's data: a trained avatar's Gaussians once, and per frame only what changes.

A frame of any representation is given as its world-space Gaussians (what ``TrainedAvatar.pose`` returns) and the
posed mesh they ride on, each Gaussian on one triangle. The codec expresses each Gaussian in its triangle's local
frame (:func:`avatar.geometry.frames.triangle_frames`: ``mu = k R mu_i + T``, ``s = k s_i``, ``q = R q_i``) and
stores:

- once (:class:`StaticGaussians`): per Gaussian its triangle, mesh part, local mean, log-scale and rotation, colour
  and opacity: the per-Gaussian median over sampled frames, so the Gaussians that nothing moves in their frame (all
  of a GaussianAvatars model) are exact in every frame;
- per frame: the posed vertices, quantised to 16 bits over the motion's bounding box, from which the viewer derives
  the triangles' frames; and :class:`Overrides`: for the Gaussians whose geometry or appearance the static values
  posed on the frame would get wrong by more than :class:`CodecConfig`'s tolerances, the difference, quantised in
  fixed steps (:data:`STEPS`): the pose-dependent deltas of H (the hand's geometry and appearance) and of I (the face
  near contact), or a SplattingAvatar's non-rigid embedding.

The buffers are byte-shuffled (each array's bytes grouped by significance) and zlib-compressed (:func:`pack_sections`):
small deltas leave the high bytes nearly constant, which deflate stores in little space.

:func:`decode_frame` is the viewer's computation in NumPy: the reference the JavaScript (``viewer/src/pose.js``)
follows step by step, and what :func:`frame_errors` measures the quantisation error with.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import torch

from avatar.geometry.frames import quaternion_multiply, rotation_to_quaternion, triangle_frames
from avatar.render.gaussians.world import WorldGaussians

#: 16-bit quantisation of the vertices over their motion's bounding box.
POSITION_LEVELS = 65535
#: Local values (in units of the triangle's scale) beyond this are not stored (float16 tops out at 65504).
LOCAL_LIMIT = 1000.0
#: The steps of the overrides' int16 deltas: mean (metres), log-scale, rotation vector (radians); colour and opacity
#: are exact 8-bit levels. Rounding moves a mean by at most 0.043 mm (half a step per axis), a 5 mm axis by 0.025 mm
#: and the surface of a Gaussian whose axes differ by 5 mm by 0.025 mm: within a quarter of the default geometry
#: tolerance. Halving the steps made the draft avatar's data 15 % larger.
STEPS = {"mean": 5e-5, "log_scale": 1e-2, "rotation": 1e-2}


@dataclass(frozen=True)
class CodecConfig:
    """When a frame stores a Gaussian's geometry or appearance itself instead of posing its static values on the
    frame's triangles."""

    # a geometry override where the posed static Gaussian is off by more than this (mm): its mean, an axis' length,
    # or its rotation times the difference of its longest and shortest axes (how far the rotation moves its surface)
    # (0.2 mm: a tenth of a pixel of draft's 128 px crops; 0.1 mm and one level made the draft avatar's data 26 MB per
    # 100 frames, over the viewer's 20 MB budget: docs/notes/2026-12-06-browser-viewer.md)
    geometry_tolerance_mm: float = 0.2
    color_tolerance_levels: float = 2.0  # an appearance override where a colour channel is off by more (8-bit levels)
    opacity_tolerance_levels: float = 2.0  # or the opacity (8-bit levels)

    def problems(self) -> list[str]:
        """The settings out of range, one line each."""
        return [f"{name}={value}: must be > 0" for name, value in vars(self).items() if not value > 0]


@dataclass
class FrameGaussians:
    """World-space Gaussians of one frame as float64 arrays: means (N, 3) m, scales (N, 3) m, quats (N, 4) (w, x, y,
    z), opacities (N,) in [0, 1], colors (N, 3) in [0, 1]."""

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray

    @classmethod
    def of(cls, g: WorldGaussians) -> FrameGaussians:
        """From a representation's posed frame."""
        arrays = [np.asarray(t.detach().double().cpu().numpy()) for t in (g.means, g.scales, g.quats)]
        quats = arrays[2] / np.linalg.norm(arrays[2], axis=1, keepdims=True).clip(1e-30)
        opacity = g.opacities.detach().double().cpu().numpy().reshape(-1)
        return cls(arrays[0], arrays[1], quats, opacity, g.colors.detach().double().cpu().numpy())

    def non_finite(self) -> list[str]:
        """The attributes holding a NaN or an infinity (empty when all are finite)."""
        return [name for name, values in vars(self).items() if not np.isfinite(values).all()]


@dataclass
class StaticGaussians:
    """What the viewer loads once, N Gaussians: ``triangle`` (N,) u32, ``part`` (N,) u8, ``local_means`` (N, 3) f16
    (units of the frame scale k: float16 places a mean within 0.05 % of k of its value), ``local_log_scales`` (N, 3)
    f16 (log of units of k), ``local_quats`` (N, 4) f16, ``rgba`` (N, 4) u8."""

    triangle: np.ndarray
    part: np.ndarray
    local_means: np.ndarray
    local_log_scales: np.ndarray
    local_quats: np.ndarray
    rgba: np.ndarray


@dataclass
class Overrides:
    """What one frame stores beyond the static Gaussians posed on its vertices: ``geometry`` (G,) u32 indices with
    int16 deltas (in :data:`STEPS`) of their mean ``d_mean`` (G, 3), log-scale ``d_log_scale`` (G, 3) and rotation
    ``d_rotation`` (G, 3) (a world-space rotation vector applied before the posed rotation); ``appearance`` (A,)
    u32 indices with the int16 deltas of their 8-bit colour and opacity ``d_rgba`` (A, 4)."""

    geometry: np.ndarray
    d_mean: np.ndarray
    d_log_scale: np.ndarray
    d_rotation: np.ndarray
    appearance: np.ndarray
    d_rgba: np.ndarray


@dataclass
class Ranges:
    """A motion's vertex box ``vertex_lo``/``vertex_hi`` (3,) (metres), which its vertices are quantised over."""

    vertex_lo: np.ndarray
    vertex_hi: np.ndarray

    @classmethod
    def of(cls, vertices: np.ndarray) -> Ranges:
        """The box of the motion's ``vertices`` (T, V, 3) (a degenerate extent widened: every step is finite)."""
        return cls(*_widened(vertices.reshape(-1, 3).min(0), vertices.reshape(-1, 3).max(0)))

    def to_json(self) -> dict[str, list[float]]:
        return {"vertex_lo": self.vertex_lo.tolist(), "vertex_hi": self.vertex_hi.tolist()}


def _widened(lo: np.ndarray, hi: np.ndarray, minimum: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) with every extent at least ``minimum`` (a constant coordinate still quantises)."""
    pad = np.maximum(minimum - (hi - lo), 0.0) / 2
    return lo - pad, hi + pad


def quantise_vertices(vertices: np.ndarray, ranges: Ranges) -> np.ndarray:
    """(..., V, 3) metres in the motion's box -> u16 (rounded to the nearest of POSITION_LEVELS steps, clipped)."""
    span = ranges.vertex_hi - ranges.vertex_lo
    return np.rint((vertices - ranges.vertex_lo) / span * POSITION_LEVELS).clip(0, POSITION_LEVELS).astype(np.uint16)


def differences_in_time(q: np.ndarray) -> np.ndarray:
    """(T, ...) u16 -> the first frame, then each frame minus the one before, modulo 2^16 (small numbers when the
    motion is smooth, which deflate stores in less space)."""
    return np.diff(q.astype(np.int64), axis=0, prepend=0).astype(np.uint16)


def sums_in_time(d: np.ndarray) -> np.ndarray:
    """The inverse of :func:`differences_in_time`."""
    return np.cumsum(d.astype(np.int64), axis=0).astype(np.uint16)


def dequantise_vertices(q: np.ndarray, ranges: Ranges) -> np.ndarray:
    """The inverse of :func:`quantise_vertices`: (..., V, 3) u16 -> metres (float64)."""
    return ranges.vertex_lo + q.astype(np.float64) * ((ranges.vertex_hi - ranges.vertex_lo) / POSITION_LEVELS)


def _frames(vertices: np.ndarray, faces: np.ndarray, triangle: np.ndarray) -> tuple[np.ndarray, ...]:
    """(origin (N, 3), rotation (N, 3, 3), scale (N,), rotation as quaternion (N, 4)) of each Gaussian's triangle
    on ``vertices`` (V, 3), float64."""
    frames = triangle_frames(
        torch.from_numpy(np.asarray(vertices, np.float64)), torch.from_numpy(faces.astype(np.int64))
    )
    index = torch.from_numpy(triangle.astype(np.int64))
    rotation = frames.rotation[index]
    return (
        frames.origin[index].numpy(),
        rotation.numpy(),
        frames.scale[index].numpy(),
        rotation_to_quaternion(rotation).numpy(),
    )


def _multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return quaternion_multiply(torch.from_numpy(a), torch.from_numpy(b)).numpy()


def _conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def to_levels(values: np.ndarray) -> np.ndarray:
    """Values in [0, 1] -> 8-bit levels (u8, clipped): colours and opacities as the viewer stores them."""
    return np.rint(np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)


def local_gaussians(
    frame: FrameGaussians, vertices: np.ndarray, faces: np.ndarray, triangle: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``frame``'s Gaussians in their triangles' frames on ``vertices`` (V, 3): local means (N, 3), log-scales
    (N, 3) and unit quaternions (N, 4), float64."""
    origin, rotation, scale, frame_quat = _frames(vertices, faces, triangle)
    local_means = np.einsum("nji,nj->ni", rotation, frame.means - origin) / scale[:, None]
    local_log_scales = np.log(frame.scales.clip(1e-30)) - np.log(scale)[:, None]
    local_quats = _multiply(_conjugate(frame_quat), frame.quats)
    return local_means, local_log_scales, local_quats / np.linalg.norm(local_quats, axis=1, keepdims=True)


def static_gaussians(
    samples: list[tuple[FrameGaussians, np.ndarray]], faces: np.ndarray, face_part: np.ndarray, triangle: np.ndarray
) -> StaticGaussians:
    """The per-Gaussian median of the local values over ``samples`` (frame, its vertices (V, 3)): exact wherever a
    Gaussian does not move in its triangle's frame."""
    means, logs, quats = zip(*(local_gaussians(f, v, faces, triangle) for f, v in samples))
    q = np.stack(quats)  # (S, N, 4): one sign per Gaussian (the first sample's hemisphere) before the median
    q = q * np.where((q * q[:1]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    median_q = np.median(q, axis=0)
    median_q /= np.linalg.norm(median_q, axis=1, keepdims=True).clip(1e-30)
    local_means = np.median(np.stack(means), axis=0)
    # a Gaussian on a degenerate triangle (its scale k clamped to 1e-6) lies millions of k from it: float16 cannot
    # hold that, so it is stored at the triangle's centroid and every frame overrides it (encode_overrides)
    unbound = ~np.isfinite(local_means).all(1) | (np.abs(local_means).max(1) > LOCAL_LIMIT)
    local_means[unbound] = 0.0
    local_logs = np.clip(np.median(np.stack(logs), axis=0), -LOCAL_LIMIT, LOCAL_LIMIT)
    colors = np.median(np.stack([f.colors for f, _ in samples]), axis=0)
    opacities = np.median(np.stack([f.opacities for f, _ in samples]), axis=0)
    return StaticGaussians(
        triangle=triangle.astype(np.uint32),
        part=face_part[triangle].astype(np.uint8),
        local_means=local_means.astype(np.float16),
        local_log_scales=local_logs.astype(np.float16),
        local_quats=median_q.astype(np.float16),
        rgba=np.concatenate([to_levels(colors), to_levels(opacities)[:, None]], axis=1),
    )


def pose_static(static: StaticGaussians, vertices: np.ndarray, faces: np.ndarray) -> FrameGaussians:
    """The static Gaussians on the frames of the triangles of ``vertices`` (V, 3): the viewer's computation."""
    origin, rotation, scale, frame_quat = _frames(vertices, faces, static.triangle)
    local_means = static.local_means.astype(np.float64)
    means = scale[:, None] * np.einsum("nij,nj->ni", rotation, local_means) + origin
    scales = np.exp(static.local_log_scales.astype(np.float64)) * scale[:, None]
    quats = _multiply(frame_quat, static.local_quats.astype(np.float64))
    rgba = static.rgba.astype(np.float64) / 255
    return FrameGaussians(means, scales, quats / np.linalg.norm(quats, axis=1, keepdims=True), rgba[:, 3], rgba[:, :3])


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) angle between unit quaternions ``a`` and ``b`` (N, 4), degrees."""
    return np.degrees(2 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)))


def _steps(delta: np.ndarray, step: float) -> np.ndarray:
    return np.rint(delta / step).clip(-32767, 32767).astype(np.int16)


def rotation_vector(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions -> (N, 3) rotation vectors (axis times angle in [0, pi])."""
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    sin_half = np.linalg.norm(q[:, 1:], axis=1, keepdims=True)
    angle = 2 * np.arctan2(sin_half, q[:, :1])
    return q[:, 1:] * np.where(sin_half > 1e-12, angle / np.maximum(sin_half, 1e-12), 2.0)


def rotation_quaternion(v: np.ndarray) -> np.ndarray:
    """The inverse of :func:`rotation_vector`."""
    angle = np.linalg.norm(v, axis=1, keepdims=True)
    scale = np.where(angle > 1e-12, np.sin(angle / 2) / np.maximum(angle, 1e-12), 0.5)
    return np.concatenate([np.cos(angle / 2), v * scale], axis=1)


def encode_overrides(frame: FrameGaussians, posed_static: FrameGaussians, config: CodecConfig) -> Overrides:
    """The Gaussians of ``frame`` whose geometry or appearance ``posed_static`` (the static values on this frame's
    quantised vertices) gets wrong by more than ``config``'s tolerances, and their deltas from it."""
    geometry = np.flatnonzero(geometry_error_mm(posed_static, frame) > config.geometry_tolerance_mm)
    static_rgba = _rgba_levels(posed_static)
    d_rgba = _rgba_levels(frame) - static_rgba
    appearance = np.flatnonzero(
        (np.abs(d_rgba[:, :3]).max(1) > config.color_tolerance_levels)
        | (np.abs(d_rgba[:, 3]) > config.opacity_tolerance_levels)
    )
    turn = _multiply(frame.quats[geometry], _conjugate(posed_static.quats[geometry]))
    log_ratio = np.log(frame.scales[geometry].clip(1e-30)) - np.log(posed_static.scales[geometry].clip(1e-30))
    return Overrides(
        geometry=geometry.astype(np.uint32),
        d_mean=_steps(frame.means[geometry] - posed_static.means[geometry], STEPS["mean"]),
        d_log_scale=_steps(log_ratio, STEPS["log_scale"]),
        d_rotation=_steps(rotation_vector(turn), STEPS["rotation"]),
        appearance=appearance.astype(np.uint32),
        d_rgba=d_rgba[appearance].astype(np.int16),
    )


def _rgba_levels(g: FrameGaussians) -> np.ndarray:
    """(N, 4) int: colour and opacity in 8-bit levels."""
    return np.concatenate([to_levels(g.colors), to_levels(g.opacities)[:, None]], axis=1).astype(np.int64)


def bit_mask(indices: np.ndarray, count: int) -> np.ndarray:
    """(ceil(count / 8),) u8: bit i (little-endian within each byte) set for each of ``indices``."""
    flags = np.zeros(count, dtype=bool)
    flags[indices] = True
    return np.packbits(flags, bitorder="little")


def mask_indices(mask: np.ndarray, count: int) -> np.ndarray:
    """The inverse of :func:`bit_mask`: the set bits' indices, ascending."""
    return np.flatnonzero(np.unpackbits(mask, count=count, bitorder="little"))


def decode_frame(
    static: StaticGaussians, vertices_q: np.ndarray, overrides: Overrides, ranges: Ranges, faces: np.ndarray
) -> FrameGaussians:
    """What the viewer draws for a frame: the static Gaussians on the dequantised vertices ``vertices_q`` (V, 3)
    u16, plus the overrides' deltas."""
    return apply_overrides(pose_static(static, dequantise_vertices(vertices_q, ranges), faces), overrides)


def apply_overrides(posed_static: FrameGaussians, overrides: Overrides) -> FrameGaussians:
    """A copy of ``posed_static`` (the static Gaussians posed on a frame) with the frame's overrides' deltas added."""
    g = FrameGaussians(*(np.array(values, copy=True) for values in vars(posed_static).values()))
    i = overrides.geometry.astype(np.int64)
    g.means[i] += overrides.d_mean * STEPS["mean"]
    g.scales[i] *= np.exp(overrides.d_log_scale * STEPS["log_scale"])
    g.quats[i] = _multiply(rotation_quaternion(overrides.d_rotation * STEPS["rotation"]), g.quats[i])
    a = overrides.appearance.astype(np.int64)
    rgba = (np.rint(np.concatenate([g.colors[a], g.opacities[a, None]], axis=1) * 255) + overrides.d_rgba) / 255
    g.colors[a], g.opacities[a] = rgba[:, :3].clip(0, 1), rgba[:, 3].clip(0, 1)
    return g


def geometry_error_mm(a: FrameGaussians, b: FrameGaussians) -> np.ndarray:
    """(N,) how far the Gaussians of ``a`` are from those of ``b`` (mm): the largest of the distance of their means,
    the change of an axis' length, and the rotation's angle times the difference of the longest and shortest axes
    (how far the rotation moves the surface; a round Gaussian has none)."""
    axis = np.abs(a.scales - b.scales).max(1)
    turn = np.radians(_rotation_deg(a.quats, b.quats)) * np.ptp(b.scales, axis=1)
    return np.maximum(np.maximum(np.linalg.norm(a.means - b.means, axis=1), axis), turn) * 1000


def frame_errors(decoded: FrameGaussians, truth: FrameGaussians) -> dict[str, float]:
    """How far the decoded frame is from the model's, max and mean over the Gaussians: geometry (mm,
    :func:`geometry_error_mm`), mean alone (mm), colour and opacity (8-bit levels, against the model's unrounded
    values)."""
    out: dict[str, float] = {}
    for name, values in (
        ("geometry_mm", geometry_error_mm(decoded, truth)),
        ("position_mm", np.linalg.norm(decoded.means - truth.means, axis=1) * 1000),
        ("color_levels", np.abs(decoded.colors - truth.colors.clip(0, 1)).max(1) * 255),
        ("opacity_levels", np.abs(decoded.opacities - truth.opacities) * 255),
    ):
        out[f"{name}_max"] = float(values.max()) if values.size else 0.0
        out[f"{name}_mean"] = float(values.mean()) if values.size else 0.0
    return out


def pack_sections(arrays: dict[str, np.ndarray]) -> tuple[bytes, dict[str, dict]]:
    """One zlib-compressed buffer of ``arrays`` and its table: name -> {offset, dtype, shape} (offsets into the
    decompressed buffer, each aligned to 4 bytes), which the viewer reads its typed arrays with. Each array's
    bytes are stored shuffled, grouped by significance (the first byte of every element, then the second, ...)."""
    chunks, table, offset = [], {}, 0
    for name, array in arrays.items():
        little = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False)
        data = little.view(np.uint8).reshape(-1, array.dtype.itemsize).T.tobytes()
        table[name] = {"offset": offset, "dtype": str(array.dtype), "shape": list(array.shape)}
        padded = data + b"\0" * (-len(data) % 4)
        chunks.append(padded)
        offset += len(padded)
    return zlib.compress(b"".join(chunks), 9), table


def unpack_sections(buffer: bytes, table: dict[str, dict]) -> dict[str, np.ndarray]:
    """The inverse of :func:`pack_sections`."""
    raw = zlib.decompress(buffer)
    out = {}
    for name, entry in table.items():
        dtype = np.dtype(entry["dtype"]).newbyteorder("<")
        count = int(np.prod(entry["shape"])) if entry["shape"] else 1
        planes = np.frombuffer(raw, np.uint8, count * dtype.itemsize, entry["offset"]).reshape(dtype.itemsize, count)
        out[name] = np.ascontiguousarray(planes.T).view(dtype).reshape(entry["shape"])
    return out
