"""Triangle frames and bound Gaussians against a per-triangle numpy reference and invariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from avatar.geometry.frames import place_gaussians, quaternion_multiply, rotation_to_quaternion, triangle_frames

RNG = np.random.default_rng(0)


def reference_frame(v0: np.ndarray, v1: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Gram-Schmidt in plain numpy, one triangle at a time."""
    a0 = (v1 - v0) / np.linalg.norm(v1 - v0)
    n = np.cross(v1 - v0, v2 - v0)
    a1 = n / np.linalg.norm(n)
    u = (v2 - v0) - a0 * np.dot(a0, v2 - v0)  # in-plane, perpendicular to the edge, toward v2
    a2 = -u / np.linalg.norm(u)
    k = (np.linalg.norm(v1 - v0) + np.linalg.norm(u)) / 2
    return (v0 + v1 + v2) / 3, np.stack([a0, a1, a2], axis=1), k


def test_frames_match_reference_per_triangle():
    verts = RNG.normal(size=(30, 3))
    faces = np.stack([RNG.permutation(30)[:3] for _ in range(20)])
    fr = triangle_frames(torch.tensor(verts), torch.tensor(faces))
    for f, (i, j, k) in enumerate(faces):
        origin, R, scale = reference_frame(verts[i], verts[j], verts[k])
        np.testing.assert_allclose(fr.origin[f].numpy(), origin, atol=1e-12)
        np.testing.assert_allclose(fr.rotation[f].numpy(), R, atol=1e-9)
        np.testing.assert_allclose(fr.scale[f].item(), scale, rtol=1e-9)
    R = fr.rotation
    np.testing.assert_allclose((R.transpose(-1, -2) @ R).numpy(), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(20, dtype=R.dtype))


def test_bound_gaussians_follow_rigid_motion_and_scaling():
    verts = torch.tensor(RNG.normal(size=(12, 3)))
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]])
    binding = torch.tensor([0, 0, 1, 2, 3, 3, 3])
    mu = torch.tensor(RNG.normal(size=(7, 3)))
    s = torch.tensor(RNG.uniform(0.1, 1, size=(7, 3)))
    q = torch.tensor(RNG.normal(size=(7, 4)))
    means, scales, quats = place_gaussians(triangle_frames(verts, faces), binding, mu, s, q)
    rot = Rotation.random(random_state=1)
    Rm, t, c = torch.tensor(rot.as_matrix()), torch.tensor([0.3, -1.0, 2.0]), 2.5
    moved = c * verts @ Rm.T + t
    means2, scales2, quats2 = place_gaussians(triangle_frames(moved, faces), binding, mu, s, q)
    np.testing.assert_allclose(means2.numpy(), (c * means @ Rm.T + t).numpy(), atol=1e-9)
    np.testing.assert_allclose(scales2.numpy(), (c * scales).numpy(), rtol=1e-9)
    # The world rotation of each Gaussian turns by the same rigid rotation.
    r1 = Rotation.from_quat(quats.numpy()[:, [1, 2, 3, 0]])
    r2 = Rotation.from_quat(quats2.numpy()[:, [1, 2, 3, 0]])
    np.testing.assert_allclose((r2 * r1.inv()).as_matrix(), np.broadcast_to(rot.as_matrix(), (7, 3, 3)), atol=1e-9)


def test_rotation_to_quaternion_matches_scipy_including_near_180_degrees():
    rots = Rotation.concatenate(
        [Rotation.random(200, random_state=2), Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi - 1e-9, 0], [0, 0, 0]])]
    )
    q = rotation_to_quaternion(torch.tensor(rots.as_matrix())).numpy()
    ref = rots.as_quat()[:, [3, 0, 1, 2]]
    ref *= np.where(ref[:, :1] < 0, -1, 1)
    np.testing.assert_allclose(np.abs((q * ref).sum(-1)), 1.0, atol=1e-9)  # same rotation (up to sign)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)


def test_quaternion_multiply_composes_rotations():
    a, b = Rotation.random(random_state=3), Rotation.random(random_state=4)
    wxyz = lambda r: torch.tensor(r.as_quat()[[3, 0, 1, 2]])  # noqa: E731
    ab = quaternion_multiply(wxyz(a), wxyz(b)).numpy()
    np.testing.assert_allclose(Rotation.from_quat(ab[[1, 2, 3, 0]]).as_matrix(), (a * b).as_matrix(), atol=1e-12)


@pytest.mark.parametrize(
    "tri",
    [
        [[0, 0, 0], [0, 0, 0], [0, 0, 0]],  # all vertices coincide
        [[0, 0, 0], [1, 0, 0], [2, 0, 0]],  # collinear, zero area
        [[0, 0, 0], [0, 0, 0], [0, 1, 0]],  # first edge has zero length
        [[0, 0, 0], [1e-9, 0, 0], [0, 1e-9, 0]],  # tiny
        [[0, 0, 0], [1e6, 0, 0], [0, 1e6, 0]],  # huge
    ],
    ids=["point", "collinear", "zero-edge", "tiny", "huge"],
)
def test_degenerate_triangles_give_finite_frames_and_gradients(tri):
    verts = torch.tensor(tri, dtype=torch.float64, requires_grad=True)
    fr = triangle_frames(verts, torch.tensor([[0, 1, 2]]))
    means, scales, quats = place_gaussians(
        fr,
        torch.tensor([0]),
        torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64),
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
    )
    for t in (fr.rotation, fr.scale, means, scales, quats):
        assert torch.isfinite(t).all()
    R = fr.rotation[0]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)
    assert fr.scale.item() > 0
    (means.sum() + scales.sum() + quats.sum()).backward()
    assert torch.isfinite(verts.grad).all()


def test_gradcheck_placement():
    verts = torch.tensor(RNG.normal(size=(6, 3)), requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    mu = torch.tensor(RNG.normal(size=(3, 3)), requires_grad=True)

    def fn(v: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return place_gaussians(
            triangle_frames(v, faces),
            torch.tensor([0, 1, 1]),
            m,
            torch.ones(3, 3, dtype=torch.float64),
            torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64),
        )

    assert torch.autograd.gradcheck(fn, (verts, mu))


def test_the_gradient_through_shared_frames_is_the_same_bits_on_two_threads_and_matches_float64():
    """Many Gaussians share a triangle, and (with the tracking refined) a vertex's gradient sums over all of them:
    summed by advanced indexing's backward (parallel atomic additions on the CPU) it differed from run to run on two
    threads, which made training with refine_params irreproducible. Now the same bits every time, and within float32
    rounding of the float64 gradient."""
    from avatar.geometry.gather import gather_rows

    g = torch.Generator().manual_seed(0)
    V, F, N = 500, 800, 100_000
    verts = torch.randn(V, 3, generator=g, dtype=torch.float64)
    faces = torch.randint(0, V, (F, 3), generator=g)
    binding = torch.randint(0, F, (N,), generator=g)
    local = [torch.randn(N, 3, generator=g), torch.rand(N, 3, generator=g), torch.randn(N, 4, generator=g)]
    weights = [torch.randn(N, c, generator=g, dtype=torch.float64) for c in (3, 3, 4)]

    def vertex_gradient(dtype: torch.dtype) -> torch.Tensor:
        v = verts.to(dtype).requires_grad_()
        placed = place_gaussians(triangle_frames(v, faces), binding, *(t.to(dtype) for t in local))
        sum((p * w.to(dtype)).sum() for p, w in zip(placed, weights)).backward()
        return v.grad

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        grads = [vertex_gradient(torch.float32) for _ in range(4)]
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(grads[0], other) for other in grads[1:])  # the same code, run again: exact
    reference = vertex_gradient(torch.float64)
    torch.testing.assert_close(grads[0].double(), reference, rtol=1e-3, atol=1e-3 * reference.abs().max().item())
    index = torch.tensor([[2, 0], [1, 1]])
    rows = torch.arange(12.0).reshape(2, 3, 2)
    # as advanced indexing, any axis; both only copy values (no arithmetic), so equal bit for bit on any CPU
    assert torch.equal(gather_rows(rows, index, dim=1), rows[:, index, :])
