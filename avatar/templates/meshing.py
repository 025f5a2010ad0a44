"""Small mesh-construction helpers for the procedural templates.

:class:`MeshBuilder` collects points and quad / triangle faces, keeps every
new batch of faces winding-consistent with the faces already there (through
the shared edges), and at the end drops unused points, splits quads along their
shorter diagonal and orients the closed surface outward.
"""

from __future__ import annotations

import numpy as np


class MeshBuilder:
    """Accumulates a closed polygon mesh with consistent winding."""

    def __init__(self) -> None:
        self._points: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []
        self._count = 0
        self._polys: list[np.ndarray] = []
        self._half_edges: set[tuple[int, int]] = set()

    @property
    def points(self) -> np.ndarray:
        """(N, 3) every point added so far."""
        return np.concatenate(self._points) if self._points else np.zeros((0, 3))

    @property
    def labels(self) -> np.ndarray:
        """(N,) the integer label given with each point."""
        return np.concatenate(self._labels) if self._labels else np.zeros(0, dtype=np.int64)

    def add_points(self, points: np.ndarray, label: int = 0) -> np.ndarray:
        """(..., 3) points -> their ids, shaped like ``points[..., 0]``."""
        pts = np.asarray(points, dtype=np.float64)
        flat = pts.reshape(-1, 3)
        ids = np.arange(self._count, self._count + flat.shape[0]).reshape(pts.shape[:-1])
        self._points.append(flat)
        self._labels.append(np.full(flat.shape[0], label, dtype=np.int64))
        self._count += flat.shape[0]
        return ids

    def extend_tube(self, start: np.ndarray, rings: np.ndarray, label: int = 0) -> np.ndarray:
        """Continue a tube from the ring of ids ``start`` (N,) through new rings (K, N, 3);
        returns their ids (K, N)."""
        ids = self.add_points(rings, label)
        chain = np.concatenate((start[None], ids))
        for a, b in zip(chain[:-1], chain[1:]):
            self.add_faces(ring_quads(a, b))
        return ids

    def close_with_dome(self, start: np.ndarray, axis: np.ndarray, depth: float, label: int = 0) -> np.ndarray:
        """Round off and close the open ring of ids ``start`` (see :func:`dome`); returns the
        ids of the middle row (n - 1,), whose centre is the apex."""
        rings, middle = dome(self.points[start], axis, depth)
        last = self.extend_tube(start, rings, label)[-1]
        middle_ids = self.add_points(middle, label)
        self.add_faces(cap_quads(last, middle_ids))
        return middle_ids

    def add_faces(self, polys: np.ndarray) -> None:
        """Add (M, 3) triangles or (M, 4) quads, flipping the whole batch if its
        winding disagrees with the faces that share its edges."""
        polys = np.asarray(polys, dtype=np.int64)
        edges = {(int(a), int(b)) for poly in polys for a, b in zip(poly, np.roll(poly, -1))}
        same = len(edges & self._half_edges)
        opposite = len({(b, a) for a, b in edges} & self._half_edges)
        if same and opposite:
            raise ValueError("MeshBuilder: face batch is inconsistent with the existing winding")
        if same:
            polys = polys[:, ::-1]
            edges = {(b, a) for a, b in edges}
        if edges & self._half_edges:
            raise ValueError("MeshBuilder: non-manifold edge (an edge used twice in one direction)")
        self._half_edges |= edges
        self._polys.append(polys)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> vertices (V, 3), triangles (F, 3) oriented outward, and ``remap``
        (N,) from point ids to vertex ids (-1 for dropped, unused points); the
        vertices' labels are ``labels[remap >= 0]``."""
        points = self.points
        tris = [p for p in self._polys if p.shape[1] == 3]
        quads = [p for p in self._polys if p.shape[1] == 4]
        if quads:
            tris.append(split_quads(points, np.concatenate(quads)))
        faces = np.concatenate(tris)
        used = np.unique(faces)
        remap = np.full(points.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        vertices = points[used]
        faces = remap[faces]
        if signed_volume(vertices, faces) < 0:
            faces = faces[:, ::-1].copy()
        return vertices, faces, remap


def split_quads(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(M, 4) quads -> (2M, 3) triangles, each quad cut along its shorter diagonal."""
    a, b, c, d = (points[quads[:, k]] for k in range(4))
    use_ac = np.linalg.norm(a - c, axis=1) <= np.linalg.norm(b - d, axis=1)
    q = quads
    first = np.where(use_ac[:, None], q[:, [0, 1, 2]], q[:, [0, 1, 3]])
    second = np.where(use_ac[:, None], q[:, [0, 2, 3]], q[:, [1, 2, 3]])
    return np.concatenate((first, second))


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive when oriented outward)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def ring_quads(ring_a: np.ndarray, ring_b: np.ndarray) -> np.ndarray:
    """Quads joining two closed rings of equal length N: (N, 4)."""
    return np.stack((ring_a, np.roll(ring_a, -1), np.roll(ring_b, -1), ring_b), axis=1)


def cap_quads(ring: np.ndarray, middle: np.ndarray) -> np.ndarray:
    """Close a ring of N = 2n + 4 ids laid out as [top row (n + 1), right side,
    bottom row reversed (n + 1), left side] with a middle row of n - 1 new ids
    running from the left side to the right side: (2n, 4) quads."""
    n = (ring.size - 4) // 2
    if ring.size != 2 * n + 4 or n < 1 or middle.size != n - 1:
        raise ValueError(f"cap_quads needs a ring of 2n + 4 ids and n - 1 middle ids, got {ring.size}, {middle.size}")
    top = ring[: n + 1]
    bottom = ring[2 * n + 2 : n + 1 : -1]
    mid = np.concatenate(([ring[-1]], middle, [ring[n + 1]]))
    upper = np.stack((top[:-1], top[1:], mid[1:], mid[:-1]), axis=1)
    lower = np.stack((mid[:-1], mid[1:], bottom[1:], bottom[:-1]), axis=1)
    return np.concatenate((upper, lower))


def cap_middle_points(ring_points: np.ndarray, axis: np.ndarray, bulge: float) -> np.ndarray:
    """Positions of the n - 1 middle-row points of :func:`cap_quads` for a ring
    (N, 3): midpoints of facing top / bottom points pushed along ``axis`` by a
    dome profile ``bulge (1 - rho^2)`` (rho: distance from the ring centre,
    relative to the ring radius)."""
    n = (ring_points.shape[0] - 4) // 2
    top = ring_points[1:n]
    bottom = ring_points[2 * n + 1 : n + 2 : -1]
    mid = 0.5 * (top + bottom)
    centre = ring_points.mean(axis=0)
    radius = np.linalg.norm(ring_points - centre, axis=1).max()
    rho = np.linalg.norm(mid - centre, axis=1) / radius
    return mid + bulge * (1.0 - rho**2)[:, None] * axis


def triangle_quality(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """-> per-face area (F,) and smallest interior angle in degrees (F,)."""
    p = vertices[faces]
    e = [p[:, (k + 1) % 3] - p[:, k] for k in range(3)]
    area = 0.5 * np.linalg.norm(np.cross(e[0], -e[2]), axis=1)
    lengths = np.stack([np.linalg.norm(x, axis=1) for x in e], axis=1)
    angles = []
    for k in range(3):
        u, v = e[k], -e[(k + 2) % 3]
        cos = np.einsum("ij,ij->i", u, v) / np.maximum(lengths[:, k] * lengths[:, (k + 2) % 3], 1e-300)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return area, np.min(np.stack(angles, axis=1), axis=1)


def dome(ring_points: np.ndarray, axis: np.ndarray, depth: float, steps: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Round off the open end of a tube.

    ring_points (N, 3) with N = 2n + 4, unit ``axis`` pointing out of the tube,
    ``depth``: how far the apex lies beyond the ring. Returns ``steps`` shrinking
    rings (steps, N, 3) on a quarter-ellipse profile and the n - 1 middle-row
    points (n - 1, 3) that :func:`cap_quads` closes the last ring with.
    """
    centre = ring_points.mean(axis=0)
    thetas = np.linspace(0.0, 0.5 * np.pi, steps + 2)[1:-1]
    rings = np.stack([centre + np.cos(t) * (ring_points - centre) + depth * np.sin(t) * axis for t in thetas])
    middle = cap_middle_points(rings[-1], axis, depth * (1.0 - np.sin(thetas[-1])))
    return rings, middle
