"""Hand queries of the solver against brute-force references (the generator's independent mesh code)."""

from __future__ import annotations

import numpy as np
import torch

from avatar.geometry.winding import winding_number
from avatar.pbd.collision import closest_on_mesh, closest_on_triangles, query_hand
from avatar.synthetic.geometry import _closest_on_triangles as ericson_closest  # an independent formulation
from avatar.templates.layers import MANOLayer
from avatar.templates.procedural import procedural_hand


def _curled_hand() -> tuple[torch.Tensor, torch.Tensor]:
    """The procedural hand with every finger bent 1.4 rad about x (fingers dip into the palm)."""
    model = procedural_hand()
    pose = torch.zeros(1, 45, dtype=torch.float64)
    pose[0, 0::3] = 1.4
    out = MANOLayer(model)(torch.zeros(1, model.num_shapes_total, dtype=torch.float64), pose)
    return out.vertices[0], torch.tensor(model.faces)


def _points_near(verts: torch.Tensor, count: int, spread: float, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    base = verts[torch.randint(0, verts.shape[0], (count,), generator=gen)]
    return base + spread * torch.randn(count, 3, generator=gen, dtype=torch.float64)


def test_closest_point_on_triangles_matches_the_region_test_formulation() -> None:
    gen = torch.Generator().manual_seed(1)
    p, a, b, c = (torch.randn(4000, 3, generator=gen, dtype=torch.float64) for _ in range(4))
    c[:100] = a[:100] + 0.5 * (b[:100] - a[:100])  # degenerate (collinear) triangles
    ours = closest_on_triangles(p, a, b, c)
    ref = ericson_closest(p, a, b, c)
    np.testing.assert_allclose((ours - p).norm(dim=1), (ref - p).norm(dim=1), atol=1e-12)


def test_closest_on_mesh_with_candidates_equals_brute_force() -> None:
    verts, faces = _curled_hand()
    pts = _points_near(verts, 600, 0.01)
    fast, dist, face = closest_on_mesh(pts, verts, faces)
    _, brute, _ = closest_on_mesh(pts, verts, faces, candidates=faces.shape[0])
    np.testing.assert_allclose(dist, brute, atol=1e-12)
    np.testing.assert_allclose((fast - pts).norm(dim=1), dist, atol=1e-12)
    tri = verts[faces[face]]  # the returned triangle holds the returned point
    on_plane = ((fast - tri[:, 0]) * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1)).sum(1)
    assert on_plane.abs().max() < 1e-12


def test_inside_test_equals_the_winding_number_of_every_point() -> None:
    verts, faces = _curled_hand()
    pts = _points_near(verts, 800, 0.008, seed=2)
    q = query_hand(pts, verts, faces, max_depth=0.02)
    ref = winding_number(pts, verts, faces) > 0.5
    assert q.inside.sum() > 50 and (~q.inside).sum() > 50
    assert torch.equal(q.inside, ref)
    assert torch.equal(q.depth > 0, ref)
