"""Edge adjacency and triangle walking: continuity across edges, and never off the mesh."""

from __future__ import annotations

import pytest
import torch

from avatar.representations.embedded import EmbeddedGaussians
from avatar.representations.embedded.embedding import PARAM_NAMES
from avatar.representations.embedded.walking import build_walk_table, edge_neighbours, full_barycentric, walk
from tests.representations.embedded.meshes import bumpy, deform, grid, hand_and_head, template


def _model(
    verts: torch.Tensor,
    faces: torch.Tensor,
    per_triangle: int = 2,
    seed: int = 0,
    face_part: torch.Tensor | None = None,
) -> EmbeddedGaussians:
    face_part = torch.zeros(faces.shape[0], dtype=torch.long) if face_part is None else face_part
    return EmbeddedGaussians.on_triangles(verts, faces, face_part, per_triangle, init_opacity=0.2, seed=seed)


def _assert_reciprocal(faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    nbr, slot = edge_neighbours(faces)
    f, k = torch.nonzero(nbr >= 0, as_tuple=True)
    g, m = nbr[f, k], slot[f, k]
    assert torch.equal(nbr[g, m], f) and torch.equal(slot[g, m], k)
    shared = torch.stack([faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]], -1).sort(-1).values
    across = torch.stack([faces[g, (m + 1) % 3], faces[g, (m + 2) % 3]], -1).sort(-1).values
    assert torch.equal(shared, across)
    return nbr, slot


def test_edge_neighbours_of_an_open_grid_and_closed_templates():
    _, faces = grid(4)
    nbr, _ = _assert_reciprocal(faces)
    assert int((nbr < 0).sum()) == 4 * 3  # the square's outline: 3 edges a side
    for name in ("hand", "head"):
        _, faces = template(name)
        nbr, _ = _assert_reciprocal(faces)
        assert bool((nbr >= 0).all()), name  # watertight


def test_non_manifold_edges_link_every_face_and_duplicates_are_boundaries():
    fan = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three faces on edge (0, 1)
    nbr, slot = edge_neighbours(fan)
    assert nbr[:, 2].tolist() == [1, 2, 0] and slot[:, 2].tolist() == [2, 2, 2]
    duplicate = torch.tensor([[0, 1, 2], [2, 1, 0]])
    nbr, _ = edge_neighbours(duplicate)
    assert bool((nbr < 0).all())
    degenerate = torch.tensor([[0, 0, 1], [0, 1, 2]])
    nbr, _ = edge_neighbours(degenerate)
    assert nbr[0, 2] < 0 and nbr[1, 2] == 0  # the collapsed edge (0, 0) is a boundary, (0, 1) links
    assert not bool((nbr == torch.arange(2)[:, None]).any())  # no face is its own neighbour


def test_on_a_flat_mesh_walking_keeps_the_world_position_exactly():
    """Unfolding is an isometry: in a plane, any walk that meets no boundary leaves the point where it was."""
    verts, faces = grid(6)
    model = _model(verts, faces, per_triangle=4, seed=1)
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        model.displacement.copy_(0.01 * torch.randn(model.num_gaussians, generator=gen, dtype=torch.float64))
        model.barycentric.add_(0.6 * torch.randn(model.barycentric.shape, generator=gen, dtype=torch.float64))
    before, _, _ = model.world(verts, faces)
    changed = model.walk()
    after, _, _ = model.world(verts, faces)
    inside_square = (before[:, :2].abs() < 0.2 - 1e-9).all(-1)
    assert int((changed & inside_square).sum()) > 20
    torch.testing.assert_close(after[inside_square], before[inside_square], atol=1e-12, rtol=0)
    # points pushed off the square stop on its outline
    off = ~inside_square
    assert bool(off.any())
    on_outline = (after[off, :2].abs().amax(-1) - 0.2).abs() < 1e-9
    assert bool(on_outline.all())


def _edge_crossers(model: EmbeddedGaussians, faces: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Put Gaussian i on face i just inside its edge opposite vertex 2 (w = delta) and return (inside
    barycentrics, barycentrics pushed to w = -delta), for faces whose edge has a neighbour."""
    nbr, _ = edge_neighbours(faces)
    rows = torch.nonzero(nbr[model.triangle, 2] >= 0).flatten()
    u = 0.3 + 0.4 * torch.rand(len(rows), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    inside = torch.stack([u * (1 - delta), (1 - u) * (1 - delta)], -1)
    outside = torch.stack([u * (1 + delta), (1 - u) * (1 + delta)], -1)
    return rows, inside, outside


@pytest.mark.parametrize("mesh", ["bumpy grid", "hand"])
def test_walking_across_an_edge_is_continuous_on_canonical_and_posed_meshes(mesh):
    """A Gaussian pushed a distance ~delta over an edge lands on the neighbour with its world position
    (and rotation) changed by O(delta) only: by < 10 delta L (L its triangle's longest edge; the bound is
    reached at sharp creases only, the median is well below), and by 100 times less at delta / 100."""
    verts, faces = (bumpy(grid(5)[0]), grid(5)[1]) if mesh == "bumpy grid" else template("hand")
    model = _model(verts, faces, per_triangle=1)
    with torch.no_grad():
        model.displacement.fill_(0.004)
        model.log_scales.add_(torch.linspace(-0.5, 0.5, model.num_gaussians, dtype=torch.float64)[:, None])
    carried = {name: getattr(model, name).detach().clone() for name in PARAM_NAMES if name != "barycentric"}
    corners = verts[faces[model.triangle]]
    longest = (corners - corners.roll(1, dims=1)).norm(dim=-1).amax(-1)
    jumps = {}
    for delta in (1e-3, 1e-5):
        rows, inside, outside = _edge_crossers(model, faces, delta)
        with torch.no_grad():
            model.barycentric[rows] = outside
        triangle = model.triangle.clone()
        for name, posed in (("canonical", verts), ("posed", deform(verts))):
            with torch.no_grad():
                placed_before = model.world(posed, faces)
                state = (model.triangle.clone(), model.barycentric.clone())
                changed = model.walk()
                placed_after = model.world(posed, faces)
                model.triangle.copy_(state[0])
                model.barycentric.copy_(state[1])
            assert torch.equal(torch.nonzero(changed).flatten(), rows)  # each pushed one crossed, only them
            shift = (placed_after[0] - placed_before[0])[rows].norm(dim=-1) / (delta * longest[rows])
            turn = (placed_after[2] - placed_before[2])[rows].norm(dim=-1) / delta  # w >= 0 on both sides
            jumps[name, delta] = shift, turn
        assert torch.equal(model.triangle, triangle)
        with torch.no_grad():
            model.barycentric[rows] = inside
    for name, value in carried.items():  # walking moves only (triangle, u, v)
        assert torch.equal(getattr(model, name).detach(), value), name
    for name in ("canonical", "posed"):
        (coarse, coarse_turn), (fine, fine_turn) = jumps[name, 1e-3], jumps[name, 1e-5]
        assert float(coarse.max()) < 10 and float(coarse.median()) < 0.5, (name, coarse.max(), coarse.median())
        assert float(fine.max()) < 10 and float(fine_turn.max()) < 10 + 2 * float(coarse_turn.max())
        torch.testing.assert_close(fine, coarse, atol=0.05, rtol=0.05)  # linear in delta: continuous at the edge


@pytest.mark.parametrize("mesh", ["hand", "head", "hand and head with holes", "grid"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_after_any_step_every_gaussian_is_on_a_valid_triangle(mesh, dtype):
    face_part = None
    if mesh == "grid":
        verts, faces = grid(5)
    elif mesh.startswith("hand and head"):
        verts, faces, face_part = hand_and_head()
    else:
        verts, faces = template(mesh)
    model = _model(verts.to(dtype), faces, per_triangle=1, seed=4, face_part=face_part)
    part = model.part.clone()
    gen = torch.Generator().manual_seed(5)
    for scale in (0.3, 3.0, 30.0):
        with torch.no_grad():
            model.barycentric.add_(scale * torch.randn(model.barycentric.shape, generator=gen, dtype=dtype))
        model.walk(max_hops=16)
        uv = model.barycentric.detach().double()
        assert bool(((model.triangle >= 0) & (model.triangle < faces.shape[0])).all())
        assert bool((uv >= -1e-6).all()) and bool((uv.sum(-1) <= 1 + 1e-6).all()), mesh
        assert bool(torch.isfinite(uv).all())
        if face_part is not None:  # Gaussians never walk onto another part
            assert torch.equal(face_part[model.triangle], part)
    assert torch.equal(model.part, part)


def test_walk_function_leaves_inside_points_bit_identical():
    verts, faces = template("head")
    table = build_walk_table(verts, faces)
    gen = torch.Generator().manual_seed(6)
    bary = torch.distributions.Dirichlet(torch.ones(3)).sample((500,)).double()
    tri = torch.randint(faces.shape[0], (500,), generator=gen)
    uv = bary[:, :2].clone()
    uv[::2] += 0.5 * torch.randn(250, 2, generator=gen, dtype=torch.float64)
    new_tri, new_uv = walk(table, tri, uv)
    stayed = full_barycentric(uv).min(-1).values >= 0
    assert torch.equal(new_uv[stayed], uv[stayed]) and torch.equal(new_tri[stayed], tri[stayed])
    assert bool((full_barycentric(new_uv) >= 0).all())
