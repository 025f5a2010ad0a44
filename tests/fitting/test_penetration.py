"""The interpenetration proxy against a brute-force version and finite differences."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from avatar.fitting.penetration import contact_depth, find_contact_pairs

RADIUS = 0.3


def _sphere() -> tuple[torch.Tensor, torch.Tensor]:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    return torch.as_tensor(mesh.vertices)[None], torch.as_tensor(mesh.faces, dtype=torch.int64)


def _brute_force(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Depth of each point behind its nearest vertex's area-weighted normal, loop by loop."""
    normals = np.zeros_like(verts)
    for f in faces:
        n = np.cross(verts[f[1]] - verts[f[0]], verts[f[2]] - verts[f[0]])
        for v in f:
            normals[v] += n
    depth = np.zeros(len(points))
    for i, p in enumerate(points):
        j = int(np.argmin([np.linalg.norm(p - v) for v in verts]))
        offset = p - verts[j]
        if np.linalg.norm(offset) < RADIUS:
            depth[i] = max(0.0, -offset @ (normals[j] / np.linalg.norm(normals[j])))
    return depth


def test_depth_matches_brute_force_inside_outside_and_far() -> None:
    verts, faces = _sphere()
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(40, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(0.75, 1.5, size=(40, 1))  # inside, near the surface, and too far to count
    points = torch.as_tensor(directions * radii)[None]
    pairs = find_contact_pairs(points, verts, RADIUS)
    depth = np.zeros(40)
    depth[pairs.point.numpy()] = contact_depth(points, verts, faces, pairs, RADIUS).numpy()
    expected = _brute_force(points[0].numpy(), verts[0].numpy(), faces.numpy())
    np.testing.assert_allclose(depth, expected, atol=1e-12)
    assert (expected > 0.1).any() and (expected == 0).any()


def test_gradient_matches_finite_differences() -> None:
    verts, faces = _sphere()
    points = torch.as_tensor([[[0.0, 0.0, 0.9], [0.5, 0.5, 0.55], [0.1, -0.95, 0.0]]], dtype=torch.float64)
    pairs = find_contact_pairs(points, verts, RADIUS)
    assert pairs.frame.numel() == 3
    torch.autograd.gradcheck(
        lambda p, v: contact_depth(p, v, faces, pairs, RADIUS),
        (points.clone().requires_grad_(), (verts * 1.01).requires_grad_()),
    )


def test_no_pairs_and_frames_are_independent() -> None:
    verts, faces = _sphere()
    far = torch.full((1, 4, 3), 5.0, dtype=torch.float64)
    pairs = find_contact_pairs(far, verts, RADIUS)
    assert pairs.frame.numel() == 0
    assert contact_depth(far, verts, faces, pairs, RADIUS).shape == (0,)
    two = torch.cat((far, torch.zeros(1, 4, 3, dtype=torch.float64)))  # frame 1: points at the centre
    surfaces = torch.cat((verts, verts * 0.1))  # ... of a sphere of 10 cm radius
    pairs = find_contact_pairs(two, surfaces, RADIUS)
    assert set(pairs.frame.tolist()) == {1}
    torch.testing.assert_close(
        contact_depth(two, surfaces, faces, pairs, RADIUS),
        torch.full((4,), 0.1, dtype=torch.float64),
        rtol=0,
        atol=1e-3,
    )  # icosphere: 0.1 within 1 mm
