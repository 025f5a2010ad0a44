"""Stiffness from tissue thickness and stiffness files; the offset frame convention at the DECAF boundary;
errors against a reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from avatar.pbd import StiffnessFileError, face_relative_stiffness, moving_vertex_errors, world_to_decaf_offsets
from avatar.pbd.stiffness import FALLBACK_THICKNESS_M
from avatar.templates.decaf import decaf_world_offsets


def test_thin_tissue_is_stiffer_and_thickness_zero_stays_finite() -> None:
    thickness = np.array([0.0, 0.005, 0.01, 0.02])
    rel, source = face_relative_stiffness(4, thickness, None, 0.01, 1.0)
    assert source == "template"
    assert np.all(np.isfinite(rel)) and np.all(np.diff(rel) < 0)
    assert rel[2] == pytest.approx(1.0)


def test_fallback_is_uniform_without_thickness_or_file() -> None:
    rel, source = face_relative_stiffness(5, None, None, 0.01, 1.0)
    assert source == "fallback_uniform"
    np.testing.assert_allclose(rel, 0.01 / FALLBACK_THICKNESS_M)


def test_stiffness_files(tmp_path: Path) -> None:
    np.save(tmp_path / "thick.npy", np.full(3, 0.02))
    rel, source = face_relative_stiffness(3, None, tmp_path / "thick.npy", 0.01, 1.0)
    assert source == "file:thick.npy"
    np.testing.assert_allclose(rel, 0.5)
    np.savez(tmp_path / "k.npz", stiffness=np.array([0.0, 1.0, 2.0]))
    rel, _ = face_relative_stiffness(3, np.ones(3), tmp_path / "k.npz", 0.01, 1.0)  # the file wins
    np.testing.assert_allclose(rel, [0.0, 1.0, 2.0])
    for name, body, message in (
        ("short.npy", np.ones(2), "head model has 3 vertices"),
        ("neg.npy", -np.ones(3), "non-negative"),
    ):
        np.save(tmp_path / name, body)
        with pytest.raises(StiffnessFileError, match=message):
            face_relative_stiffness(3, None, tmp_path / name, 0.01, 1.0)
    np.savez(tmp_path / "other.npz", foo=np.ones(3))
    with pytest.raises(StiffnessFileError, match="'stiffness' or 'thickness_m'"):
        face_relative_stiffness(3, None, tmp_path / "other.npz", 0.01, 1.0)
    with pytest.raises(StiffnessFileError, match="missing.npy"):
        face_relative_stiffness(3, None, tmp_path / "missing.npy", 0.01, 1.0)


def test_world_and_decaf_canonical_offsets_round_trip() -> None:
    rng = np.random.default_rng(0)
    orient = rng.normal(size=(4, 3))
    world = rng.normal(scale=1e-3, size=(4, 7, 3))
    canonical = world_to_decaf_offsets(world, orient)
    np.testing.assert_allclose(decaf_world_offsets(canonical, orient), world, atol=1e-15)
    # the two conventions give the same deformed vertices: posed + world == posed - R_g canonical
    posed = rng.normal(size=(4, 7, 3))
    R = Rotation.from_rotvec(orient).as_matrix()
    np.testing.assert_allclose(posed + world, posed - np.einsum("tij,tvj->tvi", R, canonical), atol=1e-15)


def test_moving_vertex_errors_counts_vertices_moving_in_either() -> None:
    ref = np.zeros((2, 3, 3))
    pred = np.zeros((2, 3, 3))
    ref[0, 0, 0] = 0.002  # moves in the reference only
    pred[0, 1, 1] = 0.001  # moves in the prediction only
    ref[1, 2, 2] = 0.005  # not a contact frame: ignored
    e = moving_vertex_errors(pred, ref, np.array([True, False]))
    assert e is not None and e.vertices == 2
    assert e.mean_mm == pytest.approx(1.5) and e.zero_mean_mm == pytest.approx(1.0)
    assert moving_vertex_errors(pred * 0, ref * 0, np.array([True, True])) is None
