"""Landmark embeddings: landmarks as barycentric points on mesh faces.

* :func:`embed_directions`: where rays from an origin first hit a mesh (used by
  the star-shaped procedural head).
* :func:`embed_vertices`: a vertex subset written as one-hot barycentric points.
* :data:`FLAME_VERTEX_LANDMARKS`: the fallback for the official FLAME topology
  when no embedding file is given: 68 iBUG-ordered vertex ids on the 5023-vertex
  FLAME mesh, as published in the public SAiD repository
  (``data/FLAME_landmarks.txt``, VOCASET/FLAME topology). Vertex landmarks are
  approximate; prefer the official ``flame_static_embedding.pkl`` (51 points,
  iBUG 17-67) through ``load_official_model(..., landmark_embedding=...)``.
"""

from __future__ import annotations

import numpy as np

FLAME_VERTEX_LANDMARKS = np.array(
    [
        2210,
        1963,
        3056,
        3424,
        3423,
        3421,
        3419,
        3416,
        3414,
        3635,
        3643,
        3646,
        3650,
        3652,
        2004,
        568,
        728,
        2567,
        337,
        338,
        3154,
        3712,
        3868,
        2135,
        27,
        18,
        1430,
        3560,
        3561,
        3501,
        3564,
        2751,
        2793,
        3556,
        1676,
        1623,
        2428,
        2453,
        2494,
        3631,
        2278,
        2359,
        3832,
        1343,
        1218,
        1154,
        995,
        829,
        2820,
        2864,
        2774,
        3543,
        1657,
        1749,
        1703,
        1774,
        1802,
        3503,
        2905,
        2881,
        2845,
        2787,
        3531,
        1670,
        1730,
        1804,
        3504,
        2907,
    ],
    dtype=np.int64,
)


def embed_directions(
    vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First hit of each ray ``origin + t d`` (t > 0) with the mesh (Moeller-Trumbore).

    Args: vertices (V, 3), faces (F, 3), origin (3,), directions (L, 3).
    Returns: face ids (L,) and barycentric coordinates (L, 3) (weights of the
    face's three corners). Raises ValueError if a ray misses the mesh.
    """
    a, b, c = (vertices[faces[:, k]] - origin for k in range(3))
    e1, e2 = b - a, c - a
    hit_faces, bary = [], []
    for d in directions:
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -a
        bu = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        bv = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        valid = ok & (bu >= -1e-12) & (bv >= -1e-12) & (bu + bv <= 1.0 + 1e-12) & (t > 0)
        if not valid.any():
            raise ValueError(f"landmark ray {d.tolist()} misses the mesh")
        f = int(np.flatnonzero(valid)[np.argmin(t[valid])])
        w = np.clip(np.array([1.0 - bu[f] - bv[f], bu[f], bv[f]]), 0.0, None)
        hit_faces.append(f)
        bary.append(w / w.sum())
    return np.array(hit_faces, dtype=np.int64), np.array(bary)


def embed_vertices(faces: np.ndarray, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex landmarks as (face ids (L,), one-hot barycentrics (L, 3)) on any face holding each vertex."""
    face_ids, bary = [], []
    for vid in vertex_ids:
        rows, cols = np.nonzero(faces == vid)
        if rows.size == 0:
            raise ValueError(f"landmark vertex {int(vid)} is used by no face")
        face_ids.append(int(rows[0]))
        bary.append(np.eye(3)[cols[0]])
    return np.array(face_ids, dtype=np.int64), np.array(bary)
