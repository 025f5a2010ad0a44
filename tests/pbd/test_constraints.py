"""XPBD projections against their closed forms; colouring; the residual falls over the iterations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.pbd.constraints import CollisionSet, EdgeSet, attachment_set, bending_set
from avatar.pbd.problem import FrameProblem, PBDConfig
from avatar.pbd.topology import bending_stencils, colour_constraints, unique_edges
from tests.pbd.conftest import Head, press

ALL = slice(None)


@pytest.mark.parametrize("k", [0.0, 0.5, 3.0, 1e6])
def test_edge_projection_matches_its_closed_form(k: float) -> None:
    # two unit-mass particles 1.5 apart, rest length 1: dlam = -k C / (2k + 1), each moves |dlam|
    x = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]], dtype=torch.float64)
    edges = EdgeSet(
        torch.tensor([[0, 1]]),
        torch.tensor([1.0], dtype=torch.float64),
        torch.tensor([k], dtype=torch.float64),
        torch.zeros(1, dtype=torch.float64),
    )
    edges.project(x, torch.ones(2, dtype=torch.float64), torch.tensor([0]))
    assert float(x[1, 0] - x[0, 0]) == pytest.approx(1.0 + 0.5 / (2 * k + 1), rel=1e-12)
    assert float(edges.lam[0]) == pytest.approx(-k * 0.5 / (2 * k + 1), rel=1e-12, abs=1e-15)


def test_attachment_projection_is_the_minimiser_with_unit_inertia() -> None:
    # min |x - x_start|^2 / 2 + k |x - target|^2 / 2  ->  x = (x_start + k target) / (1 + k)
    start = torch.tensor([[0.3, -0.2, 0.1], [1.0, 1.0, 1.0], [2.0, 0.0, 0.0]], dtype=torch.float64)
    target = torch.zeros(3, 3, dtype=torch.float64)
    k = torch.tensor([2.0, 0.0, 1e9], dtype=torch.float64)
    x = start.clone()
    attach = attachment_set(torch.arange(3), target, k)
    attach.project(x, torch.ones(3, dtype=torch.float64), ALL)
    np.testing.assert_allclose(x, (start + k[:, None] * target) / (1 + k[:, None]), atol=1e-9)
    before = x.clone()
    attach.project(x, torch.ones(3, dtype=torch.float64), ALL)  # a linear constraint: exact in one step
    np.testing.assert_allclose(x, before, atol=1e-12)


def test_bending_ignores_rigid_and_in_plane_motion_and_resists_folding() -> None:
    # two triangles in the z = 0 plane sharing the edge 0-1
    rest = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.4, 0.8, 0], [0.6, -0.9, 0]], dtype=torch.float64)
    bend = bending_set(torch.tensor([[0, 1, 2, 3]]), rest, 1.0)
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    moved = rest @ R.T + torch.tensor([0.3, 0.1, -2.0], dtype=torch.float64)
    assert bend.value(moved, ALL).norm() < 1e-12
    shear = rest + rest[:, :1] * torch.tensor([0.0, 0.2, 0.0], dtype=torch.float64)  # in-plane affine map
    assert bend.value(shear, ALL).norm() < 1e-12
    folded = rest.clone()
    folded[2, 2] = 0.3
    assert bend.value(folded, ALL).norm() > 0.1
    x = folded.clone()
    bend.project(x, torch.ones(4, dtype=torch.float64), ALL)
    assert bend.residual(x).max() < 1e-12  # exact: k C + lam = 0 after one projection
    assert bend.value(x, ALL).norm() < bend.value(folded, ALL).norm()


def test_degenerate_stencil_gives_finite_weights() -> None:
    rest = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.5, 0.0, 0], [0.6, -0.9, 0]], dtype=torch.float64)
    bend = bending_set(torch.tensor([[0, 1, 2, 3]]), rest, 1.0)
    assert torch.isfinite(bend.a).all() and torch.isfinite(bend.b).all()


def test_collision_planes_push_out_and_never_pull_in() -> None:
    x = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, 0.5]], dtype=torch.float64)
    planes = CollisionSet(
        torch.tensor([0, 1]),
        torch.zeros(2, 3, dtype=torch.float64),
        torch.tensor([[0.0, 0, 1], [0.0, 0, 1]], dtype=torch.float64),
    )
    planes.project(x)
    np.testing.assert_allclose(x, [[0, 0, 0], [0, 0, 0.5]])


def test_colours_share_no_vertex_and_cover_every_constraint(head: Head) -> None:
    for sets in (unique_edges(head.faces), bending_stencils(head.faces)):
        colours = colour_constraints(sets)
        assert torch.equal(torch.sort(torch.cat(colours)).values, torch.arange(sets.shape[0]))
        for rows in colours:
            verts = sets[rows].reshape(-1)
            assert verts.unique().numel() == verts.numel()
    stencils = bending_stencils(head.faces)
    assert stencils.shape[0] == unique_edges(head.faces).shape[0]  # closed mesh: every edge is interior


@pytest.mark.parametrize("method", ["jacobi", "gauss_seidel"])
def test_residual_decreases_over_the_iterations(head: Head, method: str) -> None:
    cheek = head.centre_of("cheek_left")
    hand, hand_faces = press(head, cheek, 0.004)
    free = (head.vertices - head.vertices[cheek]).norm(dim=1) < 0.03
    problem = FrameProblem(
        head.vertices,
        hand,
        hand_faces,
        head.topology,
        head.stiffness,
        free,
        head.vertices,
        PBDConfig(method=method, chebyshev_rho=0.0),
    )
    problem.detect()
    residuals = []
    for _ in range(4):
        for _ in range(25):
            problem.sweep()
        residuals.append(problem.residual())
    assert all(b < a for a, b in zip(residuals, residuals[1:])), residuals
