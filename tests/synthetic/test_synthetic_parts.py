"""Unit tests of the synthetic generator's parts (no templates needed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from avatar.synthetic.geometry import signed_distance, winding_number
from avatar.synthetic.keypoints import project_keypoints
from avatar.synthetic.noise import fbm, value_noise
from avatar.synthetic.rig import make_rig
from avatar.synthetic.shading import BACKGROUND_LINEAR, srgb_decode, srgb_encode
from avatar.synthetic.soft_tissue import FALLOFF_SIGMA_M, contact_offsets


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


def _plane(half: float = 0.035, step: float = 0.0025) -> tuple[torch.Tensor, np.ndarray]:
    xs = np.arange(-half, half + 1e-9, step)
    gx, gy = np.meshgrid(xs, xs)
    return torch.as_tensor(np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])), xs


@pytest.mark.parametrize("depth", [0.002, 0.006])
def test_soft_tissue_resolves_penetration_with_a_smooth_dent(depth: float) -> None:
    face, _ = _plane()
    hand, hand_faces = _sphere(0.012, (0.0, 0.0, 0.012 - depth))  # presses into the plane
    inner = torch.full((face.shape[0],), 0.02, dtype=torch.float64)
    offsets = contact_offsets(face, inner, hand, hand_faces)
    moved = face + offsets
    sdf, _, _ = signed_distance(moved, hand, hand_faces)
    assert sdf.min() > -1e-4  # no vertex left inside the hand
    assert offsets[:, 2].max() <= 1e-12  # pushed away from the hand (-z), never towards it
    assert -offsets[:, 2].min() >= depth * 0.9
    r = face[:, :2].norm(dim=1)
    contact_radius = np.sqrt(0.012**2 - (0.012 - depth) ** 2)
    assert (offsets[r > contact_radius + 3 * FALLOFF_SIGMA_M + 1e-9] == 0).all()
    # The dent reaches beyond the contact patch (soft tissue drags its neighbours).
    ring = (r > contact_radius + 0.002) & (r < contact_radius + 0.004)
    assert (offsets[ring, 2] < -1e-4).all()


def test_soft_tissue_compliance_and_no_contact() -> None:
    face, _ = _plane()
    hand, hand_faces = _sphere(0.012, (0.0, 0.0, 0.008))
    soft = contact_offsets(face, torch.full((face.shape[0],), 0.02, dtype=torch.float64), hand, hand_faces)
    stiff = contact_offsets(face, torch.full((face.shape[0],), 0.002, dtype=torch.float64), hand, hand_faces)
    assert soft.norm(dim=1).sum() > 2 * stiff.norm(dim=1).sum()
    far, far_faces = _sphere(0.012, (0.0, 0.0, 0.0125))
    assert (contact_offsets(face, torch.full((face.shape[0],), 0.02, dtype=torch.float64),
                            far, far_faces) == 0).all()


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
