"""The viewer's codec (avatar/viewer/codec.py) against independent references: GaussianAvatars' placement for the
local frames, closed forms for the quantisers and rotations, and round trips of every encoding."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.geometry.frames import place_gaussians, triangle_frames
from avatar.viewer.codec import (
    STEPS,
    CodecConfig,
    FrameGaussians,
    Ranges,
    bit_mask,
    decode_frame,
    dequantise_vertices,
    differences_in_time,
    encode_overrides,
    frame_errors,
    local_gaussians,
    mask_indices,
    pack_sections,
    pose_static,
    quantise_vertices,
    rotation_quaternion,
    rotation_vector,
    static_gaussians,
    sums_in_time,
    unpack_sections,
)


def _mesh(rng: np.random.Generator, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A small mesh moving rigidly and bending: vertices (T, V, 3), faces (F, 3), face part (F,)."""
    grid = np.stack(np.meshgrid(np.linspace(0, 0.1, 5), np.linspace(0, 0.1, 5)), -1).reshape(-1, 2)
    rest = np.concatenate([grid, 0.01 * rng.standard_normal((25, 1))], axis=1)
    faces = np.array([[r * 5 + c, r * 5 + c + 1, r * 5 + c + 5] for r in range(4) for c in range(4)])
    vertices = []
    for t in range(frames):
        angle = 0.3 * t
        R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        bent = rest + np.stack([0 * rest[:, 0], 0 * rest[:, 0], 0.05 * t * rest[:, 0] ** 2], 1)
        vertices.append(bent @ R.T + np.array([0.01 * t, 0.2, 0.5]))
    return np.stack(vertices), faces, (np.arange(len(faces)) >= 8).astype(np.int64)


def _bound_frames(rng: np.random.Generator, vertices: np.ndarray, faces: np.ndarray, n: int):
    """Gaussians bound to random triangles, placed on each frame by GaussianAvatars' rule (the reference)."""
    triangle = rng.integers(0, len(faces), n)
    local_means = torch.tensor(rng.uniform(-0.5, 0.5, (n, 3)))
    local_scales = torch.tensor(rng.uniform(0.05, 0.3, (n, 3)))
    quats = torch.tensor(rng.standard_normal((n, 4)))
    quats = quats / quats.norm(dim=1, keepdim=True)
    colors, opacity = rng.uniform(0, 1, (n, 3)), rng.uniform(0.1, 1, n)
    out = []
    for v in vertices:
        frames = triangle_frames(torch.tensor(v), torch.tensor(faces))
        means, scales, q = place_gaussians(frames, torch.tensor(triangle), local_means, local_scales, quats)
        out.append(FrameGaussians(means.numpy(), scales.numpy(), q.numpy(), opacity.copy(), colors.copy()))
    return triangle, out


def _quat_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(2 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0, 1)))


def test_local_gaussians_invert_gaussian_avatars_placement() -> None:
    rng = np.random.default_rng(0)
    vertices, faces, _ = _mesh(rng, 3)
    triangle, frames = _bound_frames(rng, vertices, faces, 40)
    first = local_gaussians(frames[0], vertices[0], faces, triangle)
    for t in (1, 2):  # bound Gaussians keep their local values on every frame
        later = local_gaussians(frames[t], vertices[t], faces, triangle)
        np.testing.assert_allclose(later[0], first[0], atol=1e-9)
        np.testing.assert_allclose(later[1], first[1], atol=1e-9)
        assert _quat_angle_deg(later[2], first[2]).max() < 1e-5


def test_static_gaussians_pose_exactly_and_need_no_overrides() -> None:
    rng = np.random.default_rng(1)
    vertices, faces, part = _mesh(rng, 4)
    triangle, frames = _bound_frames(rng, vertices, faces, 60)
    static = static_gaussians(list(zip(frames, vertices)), faces, part, triangle)
    np.testing.assert_array_equal(static.part, part[triangle])
    ranges = Ranges.of(vertices)
    for t, frame in enumerate(frames):
        q = quantise_vertices(vertices[t], ranges)
        posed = pose_static(static, dequantise_vertices(q, ranges), faces)
        overrides = encode_overrides(frame, posed, CodecConfig())
        assert overrides.geometry.size == 0 and overrides.appearance.size == 0
        errors = frame_errors(decode_frame(static, q, overrides, ranges, faces), frame)
        # float16 local values and 16-bit vertices: micrometres; colours within half a level
        assert errors["geometry_mm_max"] < 0.02
        assert errors["color_levels_max"] <= 0.5 + 1e-6 and errors["opacity_levels_max"] <= 0.5 + 1e-6


def test_changed_gaussians_are_overridden_within_the_tolerances() -> None:
    rng = np.random.default_rng(2)
    vertices, faces, part = _mesh(rng, 3)
    triangle, frames = _bound_frames(rng, vertices, faces, 80)
    static = static_gaussians(list(zip(frames, vertices)), faces, part, triangle)
    frame = frames[1]
    moved = rng.choice(80, 20, replace=False)
    frame.means[moved] += rng.uniform(-0.004, 0.004, (20, 3))  # H's and I's offsets: millimetres
    frame.scales[moved] *= 1.3
    frame.colors[moved[:10]] = np.clip(frame.colors[moved[:10]] + 0.1, 0, 1)
    frame.opacities[moved[10:]] *= 0.5
    ranges = Ranges.of(vertices)
    q = quantise_vertices(vertices[1], ranges)
    config = CodecConfig()
    overrides = encode_overrides(frame, pose_static(static, dequantise_vertices(q, ranges), faces), config)
    assert set(overrides.geometry.tolist()) == set(moved.tolist())
    assert set(moved.tolist()) >= set(overrides.appearance.tolist()) >= set(moved[:10].tolist())
    errors = frame_errors(decode_frame(static, q, overrides, ranges, faces), frame)
    # the overridden ones to their steps (at most 0.043 mm per mean), the rest within the tolerance
    assert errors["geometry_mm_max"] <= config.geometry_tolerance_mm
    assert errors["color_levels_max"] <= config.color_tolerance_levels + 0.5
    assert errors["opacity_levels_max"] <= config.opacity_tolerance_levels + 0.5


def test_quantised_vertices_are_within_half_a_step() -> None:
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-0.3, 0.4, (5, 30, 3))
    ranges = Ranges.of(vertices)
    step = (ranges.vertex_hi - ranges.vertex_lo) / 65535
    error = np.abs(dequantise_vertices(quantise_vertices(vertices, ranges), ranges) - vertices)
    assert (error <= step / 2 + 1e-15).all()
    flat = Ranges.of(np.zeros((2, 4, 3)))  # a degenerate box still quantises, to finite values
    assert np.isfinite(dequantise_vertices(quantise_vertices(np.zeros((2, 4, 3)), flat), flat)).all()


def test_differences_in_time_wrap_around_and_sum_back() -> None:
    q = np.array([[0, 65535, 100], [65535, 0, 100], [1, 2, 65000]], dtype=np.uint16)
    np.testing.assert_array_equal(sums_in_time(differences_in_time(q)), q)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.3, np.pi - 1e-6, np.pi])
def test_rotation_vectors_round_trip(angle: float) -> None:
    rng = np.random.default_rng(4)
    axis = rng.standard_normal((10, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    v = axis * angle
    q = rotation_quaternion(v)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(q[:, 0], np.cos(angle / 2), atol=1e-12)  # closed form
    assert _quat_angle_deg(rotation_quaternion(rotation_vector(q)), q).max() < 1e-4


def test_bit_masks_round_trip() -> None:
    for count in (1, 7, 8, 9, 1000):
        chosen = np.random.default_rng(count).choice(count, count // 3, replace=False)
        mask = bit_mask(chosen, count)
        assert mask.shape == ((count + 7) // 8,)
        np.testing.assert_array_equal(mask_indices(mask, count), np.sort(chosen))


def test_sections_round_trip_every_dtype() -> None:
    rng = np.random.default_rng(5)
    arrays = {
        "u8": rng.integers(0, 255, (7, 3)).astype(np.uint8),
        "i16": rng.integers(-32767, 32767, (5, 3)).astype(np.int16),
        "u16": rng.integers(0, 65535, (2, 9, 3)).astype(np.uint16),
        "u32": rng.integers(0, 2**32 - 1, 11).astype(np.uint32),
        "f16": rng.standard_normal((3, 4)).astype(np.float16),
        "empty": np.zeros((0, 4), dtype=np.int16),
    }
    buffer, table = pack_sections(arrays)
    assert all(entry["offset"] % 4 == 0 for entry in table.values())
    back = unpack_sections(buffer, table)
    for name, array in arrays.items():
        assert back[name].dtype == array.dtype
        np.testing.assert_array_equal(back[name], array)


def test_deltas_saturate_instead_of_wrapping() -> None:
    """A Gaussian moved farther than int16 steps reach (327 m at 5e-5 m) keeps its sign."""
    rng = np.random.default_rng(6)
    vertices, faces, part = _mesh(rng, 2)
    triangle, frames = _bound_frames(rng, vertices, faces, 5)
    static = static_gaussians(list(zip(frames, vertices)), faces, part, triangle)
    frames[0].means[0] += 1e3
    ranges = Ranges.of(vertices)
    q = quantise_vertices(vertices[0], ranges)
    overrides = encode_overrides(frames[0], pose_static(static, dequantise_vertices(q, ranges), faces), CodecConfig())
    assert (overrides.d_mean[0] == 32767).all() and STEPS["mean"] * 32767 > 1


def test_codec_config_refuses_non_positive_tolerances() -> None:
    assert CodecConfig().problems() == []
    assert CodecConfig(geometry_tolerance_mm=0).problems() == ["geometry_tolerance_mm=0: must be > 0"]
    assert len(CodecConfig(color_tolerance_levels=-1, opacity_tolerance_levels=float("nan")).problems()) == 2


def test_a_degenerate_triangle_gives_finite_local_values_and_poses_back() -> None:
    """Coincident vertices (zero area): the frame's fallbacks keep every value finite, and the static Gaussians posed
    on the same mesh are where they were."""
    rng = np.random.default_rng(7)
    vertices, faces, part = _mesh(rng, 2)
    vertices[:, faces[0, 1]] = vertices[:, faces[0, 0]]  # triangle 0 collapses to an edge
    vertices[:, faces[0, 2]] = vertices[:, faces[0, 0]]  # then to a point
    triangle, frames = _bound_frames(rng, vertices, faces, 30)
    triangle[:5] = 0
    frames = [
        FrameGaussians(f.means.copy(), f.scales.copy(), f.quats.copy(), f.opacities.copy(), f.colors.copy())
        for f in frames
    ]
    static = static_gaussians(list(zip(frames, vertices)), faces, part, triangle)
    for values in (static.local_means, static.local_log_scales, static.local_quats):
        assert np.isfinite(values.astype(np.float64)).all()
    ranges = Ranges.of(vertices)
    q = quantise_vertices(vertices[0], ranges)
    posed = pose_static(static, dequantise_vertices(q, ranges), faces)
    assert not posed.non_finite()
    overrides = encode_overrides(frames[0], posed, CodecConfig())
    assert set(range(5)) <= set(overrides.geometry.tolist())  # the collapsed triangle's Gaussians: every frame
    errors = frame_errors(decode_frame(static, q, overrides, ranges, faces), frames[0])
    assert errors["geometry_mm_max"] <= CodecConfig().geometry_tolerance_mm


def test_non_finite_gaussians_are_named() -> None:
    g = FrameGaussians(np.zeros((2, 3)), np.ones((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), np.ones(2), np.zeros((2, 3)))
    assert g.non_finite() == []
    g.means[1, 0], g.opacities[0] = np.nan, np.inf
    assert g.non_finite() == ["means", "opacities"]
