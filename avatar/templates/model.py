"""The parametric template data model shared by MANO (hand) and FLAME (head).

A :class:`TemplateModel` holds exactly the arrays of the official SMPL-family
pickles (``v_template``, ``shapedirs``, ``posedirs``, ``J_regressor``,
``weights``, ``kintree_table``, ``f``) plus a few optional extras that the rest
of the project needs (PCA pose basis, landmark embedding, soft-tissue depth,
named vertex sets).  The official files and the procedural stand-ins both end up
in this one type, so every layer runs on either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NoReturn

import numpy as np

_ROOT_PARENT = -1


def _float_array(name: str, value: object) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"TemplateModel.{name} contains NaN or Inf values")
    arr.setflags(write=False)
    return arr


def _int_array(name: str, value: object) -> np.ndarray:
    raw = np.asarray(value)
    if raw.dtype.kind not in "iu":
        if raw.dtype.kind == "f" and np.all(np.isfinite(raw)) and np.all(raw == np.round(raw)):
            raw = np.round(raw)
        else:
            raise ValueError(f"TemplateModel.{name} must hold integers, got dtype {raw.dtype}")
    arr = np.array(raw, dtype=np.int64)
    arr.setflags(write=False)
    return arr


def _normalise_kintree(kintree: np.ndarray) -> np.ndarray:
    """Root parent -> -1 (official files store it as 2**32 - 1)."""
    kt = np.array(kintree, dtype=np.int64)
    kt[0, 0] = _ROOT_PARENT
    kt.setflags(write=False)
    return kt


@dataclass(frozen=True, eq=False)
class TemplateModel:
    """A linear-blend-skinned parametric mesh (MANO or FLAME layout).

    Shapes (V vertices, J joints, S shape-space columns, F faces, L landmarks):

    * ``v_template`` (V, 3) metres; ``shapedirs`` (V, 3, S); ``posedirs``
      (V, 3, 9 (J - 1)); ``J_regressor`` (J, V) dense; ``weights`` (V, J), rows
      sum to one; ``kintree_table`` (2, J) with row 0 the parents (root -1,
      every parent index smaller than its child); ``faces`` (F, 3) int64,
      counter-clockwise seen from outside.
    * ``hands_components`` (45, 45) rows = PCA components and ``hands_mean``
      (45,): MANO only.
    * ``inner_distance`` (V,): metres from each skin vertex to the rigid inner
      surface (bones / skull), the soft-tissue depth used for PBD stiffness.
    * ``num_shape``: how many leading ``shapedirs`` columns are identity
      (FLAME: the rest are expression); defaults to S.
    * ``part_labels``: named vertex-index sets ("lips", "palm", ...).
    * ``landmark_faces`` (L,) and ``landmark_bary`` (L, 3): landmarks as
      barycentric points on faces.
    * ``tip_vertex_ids`` (5,): MANO fingertip vertices in the order thumb,
      index, middle, ring, pinky.
    * ``shape_roughness`` (num_shape, num_shape): symmetric positive
      semi-definite; ``beta^T R beta`` measures how rough an identity is (the
      procedural head: landmark-region offsets that differ from their
      neighbours'). Fitting penalises it; ``None`` (official models) for none.
    * ``num_core_shape``: how many leading identity columns form the template's
      core space (the procedural head: its 10 designed components), the space a
      fit to biased detections keeps to; ``None``: all ``num_shape``.

    Arrays are copied to float64 / int64 and frozen (read-only); construction
    raises ``ValueError`` naming the offending field on any inconsistency.
    """

    name: str
    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    kintree_table: np.ndarray
    faces: np.ndarray
    hands_components: np.ndarray | None = None
    hands_mean: np.ndarray | None = None
    inner_distance: np.ndarray | None = None
    num_shape: int | None = None
    part_labels: dict[str, np.ndarray] | None = field(default=None)
    landmark_faces: np.ndarray | None = None
    landmark_bary: np.ndarray | None = None
    tip_vertex_ids: np.ndarray | None = None
    shape_roughness: np.ndarray | None = None
    num_core_shape: int | None = None

    def __post_init__(self) -> None:
        if self.name not in ("mano", "flame"):
            raise ValueError(f"TemplateModel.name must be 'mano' or 'flame', got {self.name!r}")
        put = object.__setattr__
        for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
            put(self, key, _float_array(key, getattr(self, key)))
        put(self, "faces", _int_array("faces", self.faces))
        put(self, "kintree_table", _normalise_kintree(_int_array("kintree_table", self.kintree_table)))
        for key in ("hands_components", "hands_mean", "inner_distance", "landmark_bary", "shape_roughness"):
            if getattr(self, key) is not None:
                put(self, key, _float_array(key, getattr(self, key)))
        for key in ("landmark_faces", "tip_vertex_ids"):
            if getattr(self, key) is not None:
                put(self, key, _int_array(key, getattr(self, key)))
        if self.part_labels is not None:
            put(self, "part_labels", {k: _int_array(f"part_labels[{k!r}]", v) for k, v in self.part_labels.items()})
        if self.num_shape is None:
            put(self, "num_shape", self.num_shapes_total)
        self._validate()

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.kintree_table.shape[1])

    @property
    def num_shapes_total(self) -> int:
        """S: all shapedirs columns (identity + expression)."""
        return int(self.shapedirs.shape[2]) if self.shapedirs.ndim == 3 else -1

    @property
    def num_identity_shape(self) -> int:
        """``num_shape`` as an int (``__post_init__`` resolves ``None`` to S)."""
        assert self.num_shape is not None, "TemplateModel.num_shape is resolved in __post_init__"
        return int(self.num_shape)

    @property
    def parents(self) -> np.ndarray:
        """(J,) parent index of each joint, -1 for the root."""
        return self.kintree_table[0]

    def _validate(self) -> None:
        def fail(msg: str) -> NoReturn:
            raise ValueError(f"TemplateModel({self.name}): {msg}")

        if self.v_template.ndim != 2 or self.v_template.shape[1] != 3 or self.v_template.shape[0] < 4:
            fail(f"v_template must be (V, 3) with V >= 4, got {self.v_template.shape}")
        V = self.num_vertices
        if self.kintree_table.ndim != 2 or self.kintree_table.shape[0] != 2 or self.kintree_table.shape[1] < 1:
            fail(f"kintree_table must be (2, J), got {self.kintree_table.shape}")
        J = self.num_joints
        parents = self.parents
        if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, J)):
            fail(f"kintree_table parents must satisfy 0 <= parent[j] < j for j >= 1, got {parents.tolist()}")
        if self.shapedirs.ndim != 3 or self.shapedirs.shape[:2] != (V, 3):
            fail(f"shapedirs must be (V={V}, 3, S), got {self.shapedirs.shape}")
        if self.posedirs.shape != (V, 3, 9 * (J - 1)):
            fail(f"posedirs must be (V={V}, 3, {9 * (J - 1)}), got {self.posedirs.shape}")
        if self.J_regressor.shape != (J, V):
            fail(f"J_regressor must be (J={J}, V={V}), got {self.J_regressor.shape}")
        if self.weights.shape != (V, J):
            fail(f"weights must be (V={V}, J={J}), got {self.weights.shape}")
        row_sums = self.weights.sum(axis=1)
        if not np.allclose(row_sums, 1.0, atol=1e-6):
            worst = int(np.argmax(np.abs(row_sums - 1.0)))
            fail(f"weights rows must sum to 1 (vertex {worst} sums to {row_sums[worst]:.6f})")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.shape[0] < 1:
            fail(f"faces must be (F, 3), got {self.faces.shape}")
        if self.faces.min() < 0 or self.faces.max() >= V:
            fail(f"faces index vertices outside [0, {V})")
        if not 0 <= self.num_identity_shape <= self.num_shapes_total:
            fail(f"num_shape={self.num_shape} must lie in [0, S={self.num_shapes_total}]")
        if (self.hands_components is None) != (self.hands_mean is None):
            fail("hands_components and hands_mean must be given together")
        if self.hands_components is not None and self.hands_mean is not None:
            n = 3 * (J - 1)
            if self.hands_components.ndim != 2 or self.hands_components.shape[1] != n:
                fail(f"hands_components must be (K, {n}), got {self.hands_components.shape}")
            if self.hands_mean.shape != (n,):
                fail(f"hands_mean must be ({n},), got {self.hands_mean.shape}")
        if self.inner_distance is not None:
            if self.inner_distance.shape != (V,):
                fail(f"inner_distance must be (V={V},), got {self.inner_distance.shape}")
            if np.any(self.inner_distance < 0):
                fail("inner_distance must be non-negative")
        if (self.landmark_faces is None) != (self.landmark_bary is None):
            fail("landmark_faces and landmark_bary must be given together")
        if self.landmark_faces is not None and self.landmark_bary is not None:
            L = self.landmark_faces.shape[0]
            if self.landmark_faces.ndim != 1 or self.landmark_bary.shape != (L, 3):
                fail(
                    f"landmark_faces (L,) and landmark_bary (L, 3) disagree: {self.landmark_faces.shape}, "
                    f"{self.landmark_bary.shape}"
                )
            if L and (self.landmark_faces.min() < 0 or self.landmark_faces.max() >= self.faces.shape[0]):
                fail("landmark_faces index faces out of range")
            if not np.allclose(self.landmark_bary.sum(axis=1), 1.0, atol=1e-6):
                fail("landmark_bary rows must sum to 1")
        if self.tip_vertex_ids is not None:
            if self.tip_vertex_ids.shape != (5,) or self.tip_vertex_ids.min() < 0 or self.tip_vertex_ids.max() >= V:
                fail(f"tip_vertex_ids must be 5 vertex indices in [0, {V}), got {self.tip_vertex_ids.tolist()}")
        if self.num_core_shape is not None and not 0 <= int(self.num_core_shape) <= self.num_identity_shape:
            fail(f"num_core_shape={self.num_core_shape} must lie in [0, num_shape={self.num_shape}]")
        if self.shape_roughness is not None:
            n = self.num_identity_shape
            if self.shape_roughness.shape != (n, n) or not np.allclose(self.shape_roughness, self.shape_roughness.T):
                fail(
                    f"shape_roughness must be a symmetric (num_shape={n}, num_shape) matrix, got "
                    f"{self.shape_roughness.shape}"
                )
        for key, ids in (self.part_labels or {}).items():
            if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= V)):
                fail(f"part_labels[{key!r}] must be a 1-D array of vertex indices in [0, {V})")
