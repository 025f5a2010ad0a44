"""Unit tests of the synthetic generator's parts (no templates needed)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import torch
import trimesh

from avatar.geometry.winding import winding_number
from avatar.synthetic.geometry import signed_distance
from avatar.synthetic.keypoints import project_keypoints
from avatar.synthetic.noise import fbm, value_noise
from avatar.synthetic.rig import make_rig
from avatar.synthetic.shading import BACKGROUND_LINEAR, srgb_decode, srgb_encode
from avatar.synthetic.soft_tissue import CLEARANCE_M, REACH_M, contact_offsets, membrane_matrix, signorini_magnitudes


def test_tone_curve_round_trip_and_background_code() -> None:
    x = np.linspace(0, 1, 1001)
    code = srgb_encode(x)
    assert code.dtype == np.uint8 and code[0] == 0 and code[-1] == 255
    assert np.all(np.diff(code.astype(int)) >= 0)
    np.testing.assert_allclose(srgb_decode(code), x, atol=0.01)
    assert srgb_encode(np.array(BACKGROUND_LINEAR)) == 118
    assert srgb_encode(np.array([-1.0, 2.0, np.inf])).tolist() == [0, 255, 255]


def test_rig_layout() -> None:
    target = np.array([0.0, -0.03, 0.05])
    cams = make_rig(8, 64, target)
    assert [c.camera_id for c in cams] == [f"cam{i:02d}" for i in range(8)]
    splits = [c.split for c in cams]
    assert splits.count("test") == 1
    test = splits.index("test")
    assert 0 < test < 7  # between two train views, not an extreme one
    for cam in cams:
        rot, t = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        centre = -rot.T @ t
        assert 0.6 <= np.linalg.norm(centre - target) <= 0.9
        assert centre[2] > target[2]  # frontal hemisphere
        uv, z = cam.project(np.stack([target, target + [0.0, 0.1, 0.0]]))
        np.testing.assert_allclose(uv[0], [31.5, 31.5], atol=1e-9)  # aimed at the target (OpenCV centre)
        assert uv[1, 1] < uv[0, 1]  # world up is image up
        assert np.all(cam.dist == 0) and cam.K.dtype == np.float64


def test_noise_is_deterministic_bounded_and_seeded() -> None:
    p = torch.rand(5000, 3, generator=torch.Generator().manual_seed(0))
    a, b = value_noise(p, 40.0, 3), value_noise(p, 40.0, 3)
    assert torch.equal(a, b)
    assert a.abs().max() <= 1.0 and a.std() > 0.1
    assert not torch.equal(a, value_noise(p, 40.0, 4))
    f = fbm(p, 40.0, 3, 1)
    assert f.abs().max() <= 1.0 and torch.isfinite(f).all()


def _sphere(radius: float, centre: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    mesh = trimesh.creation.icosphere(3, radius=radius)
    return torch.as_tensor(mesh.vertices + np.asarray(centre)), torch.as_tensor(mesh.faces)


def test_signed_distance_matches_a_sphere() -> None:
    verts, faces = _sphere(0.01, (0.0, 0.0, 0.0))
    p = torch.randn(400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.01
    sdf, normal, closest = signed_distance(p, verts, faces)
    exact = p.norm(dim=1) - 0.01
    assert (sdf - exact).abs().max() < 2e-4  # faceting of the icosphere
    assert torch.allclose((closest - p).norm(dim=1), sdf.abs())
    outward = (normal * torch.nn.functional.normalize(closest, dim=1)).sum(dim=1)
    assert (outward > 0.9).all()
    clear = exact.abs() > 3e-4
    assert torch.equal((sdf < 0)[clear], (exact < 0)[clear])
    assert torch.equal((winding_number(p, verts, faces) > 0.5)[clear], (exact < 0)[clear])


def _plane(half: float = 0.035, step: float = 0.0025) -> tuple[torch.Tensor, torch.Tensor]:
    """A triangulated square (V, 3) in z = 0 and its faces (F, 3), normals along +z."""
    xs = np.arange(-half, half + 1e-9, step)
    gx, gy = np.meshgrid(xs, xs)
    n = xs.size
    corner = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    faces = np.concatenate(
        [np.stack([corner, corner + 1, corner + n + 1], 1), np.stack([corner, corner + n + 1, corner + n], 1)]
    )
    return torch.as_tensor(np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])), torch.as_tensor(faces)


def _press(depth: float, inner: float = 0.02) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A plane pressed by a 12 mm sphere ``depth`` deep: the plane, its offsets, and the sphere (vertices, faces)."""
    face, faces = _plane()
    hand, hand_faces = _sphere(0.012, (0.0, 0.0, 0.012 - depth))
    offsets = contact_offsets(face, faces, torch.full((face.shape[0],), inner, dtype=torch.float64), hand, hand_faces)
    return face, offsets, hand, hand_faces


@pytest.mark.parametrize("depth", [0.002, 0.006])
def test_soft_tissue_conforms_to_the_hand_with_a_smooth_dent(depth: float) -> None:
    face, offsets, hand, hand_faces = _press(depth)
    before, _, _ = signed_distance(face, hand, hand_faces)
    after, _, _ = signed_distance(face + offsets, hand, hand_faces)
    assert after.min() >= CLEARANCE_M - 1e-9  # no vertex inside the hand, nor closer than the clearance
    assert offsets[:, 2].max() <= 1e-12  # pushed away from the hand (-z), never towards it
    pressed = before < 0
    # The deepest vertices are pushed by the hand: on its surface, at the clearance.
    deep = pressed & (-before > 0.5 * depth)
    assert deep.any() and torch.allclose(after[deep], torch.full_like(after[deep], CLEARANCE_M), atol=1e-9)
    # Near the rim of the overlap the tension may hold the skin below the sphere (Hertz): a small gap only.
    assert after[pressed].max() < CLEARANCE_M + 0.5 * depth
    r = face[:, :2].norm(dim=1)
    contact_radius = np.sqrt(0.012**2 - (0.012 - depth) ** 2)
    assert (offsets[r > contact_radius + REACH_M + 1e-9] == 0).all()
    # The dent reaches beyond the contact patch (soft tissue drags its neighbours), deepest at the contact.
    ring = (r > contact_radius + 0.002) & (r < contact_radius + 0.004)
    assert (offsets[ring, 2] < -1e-4).all()
    assert -offsets[ring, 2].max() < -offsets[:, 2].min()


def test_soft_tissue_compliance_and_no_contact() -> None:
    _, soft, _, _ = _press(0.004, inner=0.02)
    _, stiff, _, _ = _press(0.004, inner=0.002)
    assert soft.norm(dim=1).sum() > 2 * stiff.norm(dim=1).sum()
    face, faces = _plane()
    far, far_faces = _sphere(0.012, (0.0, 0.0, 0.0125))
    assert (
        contact_offsets(face, faces, torch.full((face.shape[0],), 0.02, dtype=torch.float64), far, far_faces) == 0
    ).all()


def test_membrane_matrix_is_a_symmetric_m_matrix() -> None:
    face, faces = _plane(half=0.01)
    region = torch.arange(0, face.shape[0], 2)
    hessian = membrane_matrix(face, faces, region, torch.linspace(0.0, 0.03, face.shape[0], dtype=torch.float64))
    off = hessian - torch.diag(hessian.diagonal())
    assert torch.equal(hessian, hessian.T) and (off <= 0).all()
    assert (hessian.diagonal() + off.sum(dim=1) > 0).all()  # strictly diagonally dominant


def test_signorini_magnitudes_solve_the_contact_problem() -> None:
    """Against an independent bound-constrained minimiser (L-BFGS-B) and the KKT conditions."""
    face, faces = _plane(half=0.015)
    region = torch.arange(face.shape[0])
    hessian = membrane_matrix(face, faces, region, torch.full((face.shape[0],), 0.02, dtype=torch.float64))
    pressed = torch.tensor([70, 71, 72, 83, 84, 85, 96, 97, 98, 110])  # around the centre of the 13 x 13 grid
    minimum = torch.tensor([2.0, 0.1, 1.5, 0.2, 3.0, 0.3, 1.0, 2.5, 0.05, 0.4], dtype=torch.float64) * 1e-3
    w = signorini_magnitudes(hessian, pressed, minimum)
    force = hessian @ w
    scale = force.abs().max()
    assert (w[pressed] >= minimum - 1e-15).all()
    contact = torch.isclose(w[pressed], minimum, rtol=0, atol=1e-15)
    assert contact.any() and not contact.all()  # some lift off near shallow ones
    assert (force[pressed][contact] >= -1e-9 * scale).all()  # the hand only pushes
    free = torch.ones(w.numel(), dtype=torch.bool)
    free[pressed[contact]] = False
    assert force[free].abs().max() < 1e-9 * scale  # equilibrium wherever the hand does not touch
    H = hessian.numpy()
    bounds = [(None, None)] * w.numel()
    for i, m in zip(pressed.tolist(), minimum.tolist()):
        bounds[i] = (m, None)
    ref = scipy.optimize.minimize(
        lambda v: (0.5 * v @ H @ v, H @ v),
        np.full(w.numel(), 1e-3),
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"ftol": 1e-15, "gtol": 1e-12},
    )
    np.testing.assert_allclose(w.numpy(), ref.x, atol=2e-6)


def test_keypoint_visibility_uses_depth_labels_and_image_bounds() -> None:
    cam = make_rig(2, 32, np.zeros(3))[0]
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    uv, z = cam.project(pts)
    depth, labels = np.zeros((32, 32)), np.zeros((32, 32), np.int64)
    assert project_keypoints(cam, pts[:1], depth, labels, 2, 0.04)[0, 2] == 1.0  # nothing drawn: visible
    depth[:] = z[0] - 0.02  # a surface 2 cm in front
    labels[:] = 1  # ... of another part
    kp = project_keypoints(cam, pts, depth, labels, 2, 0.04)
    np.testing.assert_allclose(kp[:, :2], uv)
    assert kp[:, 2].tolist() == [0.0, 0.0, 0.0]  # occluded, occluded, outside the image
    labels[:] = 2  # ... of the point's own part: self-occlusion within a hand's thickness
    assert project_keypoints(cam, pts[:1], depth, labels, 2, 0.04)[0, 2] == 1.0
    depth[:] = z[0] - 0.05  # own part, but deeper than the self tolerance
    assert project_keypoints(cam, pts[:1], depth, labels, 2, 0.04)[0, 2] == 0.0
    labels[:], depth[:] = 1, z[0] - 0.003
    assert project_keypoints(cam, pts[:1], depth, labels, 2, 0.04)[0, 2] == 1.0  # within tolerance
