"""World placement of mesh-embedded Gaussians: position, scale, rotation, gradients, state round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.func import functional_call

from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded.embedding import STATE_NAMES
from data_schemas.splatting import EMBEDDED_GAUSSIANS
from data_schemas.tables import read_table, write_table
from tests.representations.embedded.meshes import bumpy, deform, grid, rotation_z, template


def _model(verts: torch.Tensor, faces: torch.Tensor, per_triangle: int = 3, seed: int = 0) -> EmbeddedGaussians:
    return EmbeddedGaussians.on_triangles(
        verts, faces, torch.zeros(faces.shape[0], dtype=torch.long), per_triangle, init_opacity=0.2, seed=seed
    )


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def test_flat_triangle_point_and_normal_displacement():
    verts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    model = _model(verts, faces, per_triangle=1)
    with torch.no_grad():
        model.barycentric.copy_(torch.tensor([[0.2, 0.3]]))
        model.displacement.fill_(0.1)
    means, _, _ = model.world(verts, faces)
    # 0.2 v0 + 0.3 v1 + 0.5 v2, lifted 0.1 along the normal +z
    torch.testing.assert_close(means, torch.tensor([[0.3, 0.5, 0.1]], dtype=torch.float64))


def _brute_force_means(
    verts: np.ndarray, faces: np.ndarray, tri: np.ndarray, uv: np.ndarray, d: np.ndarray
) -> np.ndarray:
    """Loop-by-loop reference: area-weighted vertex normals, barycentric point, normal lift."""
    normals = np.zeros_like(verts)
    for f in faces:
        n = np.cross(verts[f[1]] - verts[f[0]], verts[f[2]] - verts[f[0]])
        for vid in f:
            normals[vid] += n
    out = []
    for t, (u, v), dd in zip(tri, uv, d, strict=True):
        weights = (u, v, 1.0 - u - v)
        point = sum(w * verts[faces[t][c]] for c, w in enumerate(weights))
        normal = sum(w * normals[faces[t][c]] / np.linalg.norm(normals[faces[t][c]]) for c, w in enumerate(weights))
        out.append(point + dd * normal / np.linalg.norm(normal))
    return np.array(out)


def test_world_positions_match_a_brute_force_reference_on_a_deformed_hand():
    verts, faces = template("hand")
    model = _model(verts, faces, per_triangle=1)
    gen = torch.Generator().manual_seed(1)
    pick = torch.randperm(model.num_gaussians, generator=gen)[:40]
    with torch.no_grad():
        model.displacement.copy_(0.003 * torch.randn(model.num_gaussians, generator=gen, dtype=torch.float64))
    posed = deform(verts)
    means, _, _ = model.world(posed, faces)
    ref = _brute_force_means(
        posed.numpy(),
        faces.numpy(),
        model.triangle[pick].numpy(),
        model.barycentric.detach()[pick].numpy(),
        model.displacement.detach()[pick].numpy(),
    )
    np.testing.assert_allclose(means.detach()[pick].numpy(), ref, atol=1e-12)


def test_scales_follow_the_triangle_area_change():
    verts, faces = template("head")
    model = _model(verts, faces, per_triangle=2)
    _, base, q0 = model.world(verts, faces)
    _, doubled, q2 = model.world(2.0 * verts, faces)
    torch.testing.assert_close(doubled, 2.0 * base, rtol=1e-6, atol=0)
    torch.testing.assert_close(q2, q0)
    # a stretch along x by 3 multiplies each area by (between 1 and) 3: scale by its square root
    stretched = verts * verts.new_tensor([3.0, 1.0, 1.0])
    _, s3, _ = model.world(stretched, faces)
    ratio = s3[:, 0] / base[:, 0]
    assert bool(((ratio > 1.0 - 1e-9) & (ratio < 3**0.5 + 1e-9)).all())


def test_rotation_is_identity_on_the_canonical_mesh_and_follows_a_rigid_motion():
    verts, faces = template("hand")
    model = _model(verts, faces, per_triangle=2)
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        model.quats.copy_(
            torch.nn.functional.normalize(torch.randn(model.quats.shape, generator=gen, dtype=torch.float64), dim=-1)
        )
        model.displacement.copy_(0.002 * torch.randn(model.num_gaussians, generator=gen, dtype=torch.float64))
    means0, scales0, quats0 = model.world(verts, faces)
    torch.testing.assert_close(_quat_to_matrix(quats0), _quat_to_matrix(model.quats.detach()), atol=1e-9, rtol=0)
    R0 = rotation_z(1.1) @ torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)
    shift = torch.tensor([0.3, -0.1, 0.5], dtype=torch.float64)
    means, scales, quats = model.world(verts @ R0.T + shift, faces)
    torch.testing.assert_close(means, means0 @ R0.T + shift, atol=1e-12, rtol=0)
    torch.testing.assert_close(scales, scales0)
    torch.testing.assert_close(_quat_to_matrix(quats), R0 @ _quat_to_matrix(quats0), atol=1e-9, rtol=0)


def test_world_gradients_in_u_v_d_match_finite_differences():
    verts, faces = grid(4)
    verts = bumpy(verts)
    model = _model(verts, faces, per_triangle=2, seed=3)
    posed = deform(verts)
    gen = torch.Generator().manual_seed(4)
    bary = model.barycentric.detach().clone().requires_grad_(True)
    disp = (0.01 * torch.randn(model.num_gaussians, generator=gen, dtype=torch.float64)).requires_grad_(True)

    def placed(b: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return functional_call(model, {"barycentric": b, "displacement": d}, (posed, faces))

    assert torch.autograd.gradcheck(placed, (bary, disp), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_state_tensors_round_trip_is_exact_and_fits_the_schema(tmp_path):
    verts, faces = template("head", dtype=torch.float32)
    model = _model(verts, faces, per_triangle=2, seed=5)
    gen = torch.Generator().manual_seed(6)
    with torch.no_grad():
        for name in ("displacement", "log_scales", "quats", "opacity_logits", "sh_dc"):
            getattr(model, name).add_(0.01 * torch.randn(getattr(model, name).shape, generator=gen))
    state = model.state_tensors()
    assert set(state) == set(STATE_NAMES)
    loaded = EmbeddedGaussians.from_state_tensors(state, verts, faces)
    for name, value in model.state_tensors().items():
        assert torch.equal(loaded.state_tensors()[name], value), name
    posed = deform(verts.double()).float()
    for a, b in zip(model.world(posed, faces), loaded.world(posed, faces), strict=True):
        assert torch.equal(a, b)
    part_names = ("face",)
    path = tmp_path / "embedded_gaussians.parquet"
    write_table(
        path,
        EMBEDDED_GAUSSIANS,
        {
            "triangle": state["triangle"].numpy(),
            "part": [part_names[i] for i in state["part"].tolist()],
            **{name: state[name].numpy() for name in STATE_NAMES[2:]},
        },
    )
    table = read_table(path, EMBEDDED_GAUSSIANS)
    back = {
        "triangle": torch.from_numpy(np.array(table["triangle"])),
        "part": torch.tensor([part_names.index(p) for p in table["part"]]),
        **{name: torch.from_numpy(np.array(table[name])) for name in STATE_NAMES[2:]},
    }
    again = EmbeddedGaussians.from_state_tensors(back, verts, faces)
    for name, value in state.items():
        assert torch.equal(again.state_tensors()[name], value), name


def test_from_state_tensors_refuses_triangles_outside_the_mesh():
    verts, faces = grid(3)
    state = _model(verts, faces).state_tensors()
    state["triangle"][0] = faces.shape[0]
    with pytest.raises(ValueError, match="triangle indices"):
        EmbeddedGaussians.from_state_tensors(state, verts, faces)
