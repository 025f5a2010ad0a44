"""Populating only some triangles (a face-only avatar): the chosen triangles get the same Gaussians as
when every triangle is populated, the others none."""

from __future__ import annotations

import torch

from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.embedded import EmbeddedGaussians


def _mesh() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    vertices = torch.tensor(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0.1], [2, 1, 0.2]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 5, 3]])
    return vertices, faces, torch.tensor([0, 0, 1, 1])


def test_bound_gaussians_only_on_the_populated_triangles():
    vertices, faces, part = _mesh()
    full = BoundGaussians.on_triangles(vertices, faces, part, 3, seed=1)
    some = BoundGaussians.on_triangles(vertices, faces, part, 3, seed=1, populate=part == 0)
    assert some.num_gaussians == 6 and set(some.binding.tolist()) == {0, 1} and (some.part == 0).all()
    keep = part[full.binding] == 0
    torch.testing.assert_close(some.world(vertices, faces)[0], full.world(vertices, faces)[0][keep])


def test_embedded_gaussians_only_on_the_populated_faces():
    vertices, faces, part = _mesh()
    full = EmbeddedGaussians.on_triangles(vertices, faces, part, 2, seed=1)
    some = EmbeddedGaussians.on_triangles(vertices, faces, part, 2, seed=1, populate=part == 1)
    assert some.num_gaussians == 4 and set(some.triangle.tolist()) == {2, 3}
    keep = part[full.triangle] == 1
    torch.testing.assert_close(some.world(vertices, faces)[0], full.world(vertices, faces)[0][keep])
