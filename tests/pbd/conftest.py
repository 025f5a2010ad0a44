"""Fixtures of the contact-solver tests: the procedural head at rest and a fingertip-sized sphere
pressed into it; every test runs on one torch thread (many small tensor ops)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch
import trimesh

from avatar.pbd import FaceTopology, PBDConfig
from avatar.pbd.stiffness import relative_stiffness
from avatar.templates.procedural import procedural_head


@pytest.fixture(autouse=True)
def _single_thread(one_torch_thread: None) -> None:
    """Every test here runs on one torch thread (see tests/conftest.py)."""


@dataclass(frozen=True)
class Head:
    """The procedural head at rest: vertices (V, 3) float64, faces (F, 3), relative stiffness (V,),
    vertex normals (V, 3) and the named vertex regions."""

    vertices: torch.Tensor
    faces: torch.Tensor
    stiffness: torch.Tensor
    normals: torch.Tensor
    regions: dict[str, np.ndarray]
    topology: FaceTopology

    def centre_of(self, region: str) -> int:
        """The vertex of ``region`` nearest the region's centroid."""
        idx = self.regions[region]
        pts = self.vertices[idx]
        return int(idx[int((pts - pts.mean(0)).norm(dim=1).argmin())])


@pytest.fixture(scope="session")
def head() -> Head:
    model = procedural_head()
    verts = torch.tensor(np.array(model.v_template))
    faces = torch.tensor(np.array(model.faces))
    mesh = trimesh.Trimesh(model.v_template, model.faces, process=False)
    cfg = PBDConfig()
    stiffness = torch.tensor(relative_stiffness(model.inner_distance, cfg.reference_thickness_m, cfg.stiffness_power))
    regions = {k: np.array(v) for k, v in model.part_labels.items()}
    return Head(
        verts, faces, stiffness, torch.tensor(np.array(mesh.vertex_normals)), regions, FaceTopology.build(faces)
    )


def sphere(centre: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """An outward-oriented icosphere (vertices (N, 3) float64, faces (F, 3)) around ``centre`` (3,)."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return torch.tensor(np.array(mesh.vertices)) + centre, torch.tensor(np.array(mesh.faces))


def press(head: Head, vertex: int, depth: float, radius: float = 0.008) -> tuple[torch.Tensor, torch.Tensor]:
    """A fingertip-sized sphere pressed ``depth`` metres into the skin at ``vertex``, along its normal."""
    centre = head.vertices[vertex] + (radius - depth) * head.normals[vertex]
    return sphere(centre, radius)
