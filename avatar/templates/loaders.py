"""Load the official (licensed, never shipped) MANO and FLAME model files.

``load_official_model("MANO_RIGHT.pkl", "mano")`` and
``load_official_model("generic_model.pkl", "flame")`` read the original Python 2
pickles without chumpy (see :mod:`avatar.templates.safe_pickle`) into a
:class:`TemplateModel`. Every failure (missing file, unreadable pickle, missing
keys, a file of the other kind) raises one :class:`OfficialModelError` that
names the file and says where to get the right one.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any, Literal, TypedDict

import numpy as np

from avatar.templates import safe_pickle
from avatar.templates.landmarks import FLAME_VERTEX_LANDMARKS, embed_vertices
from avatar.templates.model import TemplateModel

ModelKind = Literal["mano", "flame"]

# Official MANO fingertip vertices: thumb, index, middle, ring, pinky.
MANO_TIP_VERTEX_IDS = (745, 317, 444, 556, 673)
MANO_NUM_VERTICES = 778
FLAME_NUM_VERTICES = 5023
FLAME_NUM_SHAPE = 300  # FLAME 2020 generic_model.pkl: 300 shape + 100 expression columns

_COMMON_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
_REQUIRED = {"mano": _COMMON_KEYS + ("hands_components", "hands_mean"), "flame": _COMMON_KEYS}
_JOINTS = {"mano": 16, "flame": 5}
_HELP = {
    "mano": "download MANO_RIGHT.pkl from the MANO website (https://mano.is.tue.mpg.de) and pass "
    "model.mano_path=/path/to/MANO_RIGHT.pkl",
    "flame": "download FLAME 2020 (generic_model.pkl) from the FLAME website (https://flame.is.tue.mpg.de) and "
    "pass model.flame_path=/path/to/generic_model.pkl",
}


class _SkinningArrays(TypedDict):
    """The :class:`TemplateModel` arrays both kinds share (keyword arguments)."""

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    kintree_table: np.ndarray
    faces: np.ndarray


class OfficialModelError(ValueError):
    """The official model file is missing, unreadable or not of the requested kind."""


def _fail(path: Path, kind: str, problem: str) -> OfficialModelError:
    return OfficialModelError(f"{path}: {problem}; {_HELP.get(kind, _HELP['mano'])}")


def _read_pickle(path: Path, kind: str) -> dict[str, Any]:
    if not path.is_file():
        raise _fail(path, kind, "file not found")
    try:
        with path.open("rb") as stream:
            data = safe_pickle.load(stream)
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise _fail(path, kind, f"not a readable model pickle ({exc})") from exc
    if not isinstance(data, dict):
        raise _fail(path, kind, f"expected a dict of arrays, found {type(data).__name__}")
    return data


def _fingertips(model_vertices: np.ndarray, weights: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Tip vertices (thumb, index, middle, ring, pinky) of a non-standard MANO mesh: for
    each chain end joint (MANO ids 15, 3, 6, 12, 9), the vertex it dominates that lies
    farthest from that joint's parent."""
    tips = []
    for joint in (15, 3, 6, 12, 9):
        owned = np.flatnonzero(weights.argmax(axis=1) == joint)
        if owned.size == 0:
            owned = np.arange(model_vertices.shape[0])
        anchor = (weights[:, parents[joint]] @ model_vertices) / max(weights[:, parents[joint]].sum(), 1e-12)
        tips.append(int(owned[np.argmax(np.linalg.norm(model_vertices[owned] - anchor, axis=1))]))
    return np.array(tips, dtype=np.int64)


def load_landmark_embedding(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """FLAME landmark embedding -> (face ids (L,), barycentrics (L, 3)).

    Accepts the official ``flame_static_embedding.pkl`` (keys ``lmk_face_idx``,
    ``lmk_b_coords``) or an ``.npz`` with the same keys.
    """
    path = Path(path)
    if not path.is_file():
        raise OfficialModelError(
            f"{path}: landmark embedding not found; pass the flame_static_embedding.pkl "
            "from the FLAME website or leave it unset to use vertex landmarks"
        )
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            content = {k: data[k] for k in data.files}
    else:
        content = _read_pickle(path, "flame")
    try:
        faces = safe_pickle.to_array(content["lmk_face_idx"]).astype(np.int64).ravel()
        bary = safe_pickle.to_array(content["lmk_b_coords"]).astype(np.float64).reshape(-1, 3)
    except KeyError as exc:
        raise OfficialModelError(
            f"{path}: landmark embedding lacks key {exc}; expected lmk_face_idx and lmk_b_coords"
        ) from exc
    return faces, bary


def load_official_model(
    path: str | Path,
    kind: ModelKind,
    landmark_embedding: str | Path | None = None,
    num_shape: int | None = None,
) -> TemplateModel:
    """Read MANO_RIGHT.pkl (``kind="mano"``) or FLAME generic_model.pkl (``kind="flame"``).

    Args:
        path: the model pickle.
        kind: "mano" or "flame".
        landmark_embedding: FLAME only, optional landmark embedding file (see
            :func:`load_landmark_embedding`); without it the 68 documented vertex
            landmarks of :data:`FLAME_VERTEX_LANDMARKS` are used on the 5023-vertex mesh.
        num_shape: FLAME only, how many shapedirs columns are identity (default 300).
    """
    path = Path(path)
    if kind not in _REQUIRED:
        raise OfficialModelError(f"{path}: unknown model kind {kind!r}; expected 'mano' or 'flame'")
    data = _read_pickle(path, kind)
    missing = [key for key in _REQUIRED[kind] if key not in data]
    if missing:
        raise _fail(path, kind, f"missing keys {missing} (is this the {kind.upper()} model file?)")
    try:
        arrays = {key: safe_pickle.to_array(data[key]) for key in _REQUIRED[kind]}
    except (ValueError, KeyError, TypeError) as exc:
        raise _fail(path, kind, f"unreadable array ({exc})") from exc
    joints = arrays["kintree_table"].shape[-1] if arrays["kintree_table"].ndim == 2 else -1
    if joints != _JOINTS[kind]:
        other = "flame" if kind == "mano" else "mano"
        raise _fail(
            path,
            kind,
            f"has {joints} joints, {kind.upper()} has {_JOINTS[kind]} (a {other.upper()} file given as {kind}?)",
        )
    vertices = np.asarray(arrays["v_template"], dtype=np.float64)
    weights = np.asarray(arrays["weights"], dtype=np.float64)
    row_sums = weights.sum(axis=1, keepdims=True) if weights.ndim == 2 else None
    if row_sums is not None and 1e-9 < np.abs(row_sums - 1.0).max() < 1e-3:
        weights = weights / row_sums  # remove float32 round-off of the stored weights
    common: _SkinningArrays = {
        "v_template": vertices,
        "shapedirs": arrays["shapedirs"],
        "posedirs": arrays["posedirs"],
        "J_regressor": arrays["J_regressor"],
        "weights": weights,
        "kintree_table": arrays["kintree_table"],
        "faces": arrays["f"],
    }
    try:
        if kind == "mano":
            parents = np.asarray(arrays["kintree_table"][0], dtype=np.int64)
            tips = (
                np.array(MANO_TIP_VERTEX_IDS)
                if vertices.shape[0] == MANO_NUM_VERTICES
                else _fingertips(vertices, weights, parents)
            )
            return TemplateModel(
                name="mano",
                hands_components=arrays["hands_components"],
                hands_mean=np.ravel(arrays["hands_mean"]),
                tip_vertex_ids=tips,
                **common,
            )
        faces = np.asarray(arrays["f"], dtype=np.int64)
        if landmark_embedding is not None:
            lmk_faces, lmk_bary = load_landmark_embedding(landmark_embedding)
        elif vertices.shape[0] == FLAME_NUM_VERTICES:
            lmk_faces, lmk_bary = embed_vertices(faces, FLAME_VERTEX_LANDMARKS)
        else:
            lmk_faces, lmk_bary = None, None
        identity = FLAME_NUM_SHAPE if num_shape is None else num_shape
        return TemplateModel(
            name="flame",
            num_shape=min(identity, arrays["shapedirs"].shape[-1]),
            landmark_faces=lmk_faces,
            landmark_bary=lmk_bary,
            **common,
        )
    except ValueError as exc:
        raise _fail(path, kind, str(exc)) from exc
