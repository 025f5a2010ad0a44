"""Official-file loader: Python-2-style pickles with chumpy objects, read without chumpy."""

from __future__ import annotations

import os
import pickle
import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp

from avatar.templates import OfficialModelError, TemplateModel, load_landmark_embedding, load_official_model
from avatar.templates.landmarks import embed_vertices


@contextmanager
def fake_chumpy() -> Iterator[types.SimpleNamespace]:
    """Temporarily register modules chumpy, chumpy.ch, chumpy.reordering with classes
    Ch (value in __dict__['x']) and Reshape (operand 'a' + 'newshape'), like chumpy's own."""
    names = ("chumpy", "chumpy.ch", "chumpy.reordering")
    modules = {name: types.ModuleType(name) for name in names}
    ch_cls = type("Ch", (), {"__module__": "chumpy.ch"})
    reshape_cls = type("Reshape", (ch_cls,), {"__module__": "chumpy.reordering"})
    modules["chumpy.ch"].Ch = ch_cls
    modules["chumpy.reordering"].Reshape = reshape_cls
    modules["chumpy"].ch = modules["chumpy.ch"]
    modules["chumpy"].reordering = modules["chumpy.reordering"]
    sys.modules.update(modules)
    try:
        yield types.SimpleNamespace(Ch=ch_cls, Reshape=reshape_cls)
    finally:
        for name in names:
            del sys.modules[name]


def _ch(cls: type, **state: Any) -> Any:
    obj = cls.__new__(cls)
    obj.__dict__.update(state)
    return obj


def write_official_pickle(
    model: TemplateModel, path: Path, drop: tuple[str, ...] = (), weights_dtype: type = np.float64
) -> None:
    """Dump a model in the official key layout, with chumpy wrappers and a sparse regressor."""
    with fake_chumpy() as chumpy:
        kintree = np.array(model.kintree_table).astype(np.uint32)  # root parent -> 4294967295
        data: dict[str, Any] = {
            "v_template": _ch(chumpy.Ch, x=np.array(model.v_template), _dirty_vars=set()),
            "shapedirs": _ch(chumpy.Ch, x=np.array(model.shapedirs)),
            "posedirs": _ch(
                chumpy.Reshape, a=_ch(chumpy.Ch, x=np.array(model.posedirs).ravel()), newshape=model.posedirs.shape
            ),
            "J_regressor": sp.csc_matrix(np.array(model.J_regressor)),
            "weights": _ch(chumpy.Ch, x=np.array(model.weights).astype(weights_dtype)),
            "kintree_table": kintree,
            "f": np.array(model.faces).astype(np.uint32),
            "bs_style": "lbs",
            "bs_type": "lrotmin",
        }
        if model.hands_components is not None:
            data["hands_components"] = np.array(model.hands_components)
            data["hands_mean"] = np.array(model.hands_mean)
        for key in drop:
            del data[key]
        with path.open("wb") as stream:
            pickle.dump(data, stream, protocol=2)


def _assert_same_core(a: TemplateModel, b: TemplateModel) -> None:
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "faces"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


def test_mano_round_trip_without_chumpy(hand: TemplateModel, tmp_path: Path) -> None:
    path = tmp_path / "MANO_RIGHT.pkl"
    write_official_pickle(hand, path)
    assert "chumpy" not in sys.modules and "chumpy.ch" not in sys.modules
    loaded = load_official_model(path, "mano")
    _assert_same_core(loaded, hand)
    np.testing.assert_array_equal(loaded.hands_components, hand.hands_components)
    assert loaded.kintree_table[0, 0] == -1
    # A non-official vertex count: fingertips found from the skinning, one per finger chain.
    assert loaded.tip_vertex_ids.shape == (5,)
    np.testing.assert_allclose(
        loaded.v_template[loaded.tip_vertex_ids], hand.v_template[hand.tip_vertex_ids], atol=0.004
    )


def test_flame_round_trip_with_landmark_embedding(head: TemplateModel, tmp_path: Path) -> None:
    path = tmp_path / "generic_model.pkl"
    write_official_pickle(head, path)
    embedding = tmp_path / "flame_static_embedding.pkl"
    with embedding.open("wb") as stream:
        pickle.dump(
            {
                "lmk_face_idx": np.array(head.landmark_faces[17:]).astype(np.uint32),
                "lmk_b_coords": np.array(head.landmark_bary[17:]),
            },
            stream,
            protocol=2,
        )
    loaded = load_official_model(path, "flame", landmark_embedding=embedding, num_shape=10)
    _assert_same_core(loaded, head)
    assert loaded.num_shape == 10 and loaded.landmark_faces.shape == (51,)
    np.testing.assert_array_equal(loaded.landmark_faces, head.landmark_faces[17:])
    faces, bary = load_landmark_embedding(embedding)
    np.testing.assert_allclose(bary, head.landmark_bary[17:])


def test_missing_keys_name_the_file_and_the_fix(hand: TemplateModel, tmp_path: Path) -> None:
    path = tmp_path / "MANO_RIGHT.pkl"
    write_official_pickle(hand, path, drop=("posedirs", "hands_mean"))
    with pytest.raises(OfficialModelError, match="MANO_RIGHT.pkl") as info:
        load_official_model(path, "mano")
    assert "posedirs" in str(info.value) and "model.mano_path" in str(info.value)


def test_missing_file_and_wrong_kind(hand: TemplateModel, tmp_path: Path) -> None:
    with pytest.raises(OfficialModelError, match=r"nope\.pkl: file not found.*MANO website"):
        load_official_model(tmp_path / "nope.pkl", "mano")
    path = tmp_path / "MANO_RIGHT.pkl"
    write_official_pickle(hand, path)
    with pytest.raises(OfficialModelError, match="16 joints.*model.flame_path"):
        load_official_model(path, "flame")
    with pytest.raises(OfficialModelError, match="unknown model kind"):
        load_official_model(path, "smplx")  # type: ignore[arg-type]


class _Exploit:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (os.system, (f"touch {self.marker}",))


def test_refuses_arbitrary_code(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "MANO_RIGHT.pkl"
    with path.open("wb") as stream:
        pickle.dump({"v_template": _Exploit(marker)}, stream, protocol=2)
    with pytest.raises(OfficialModelError, match="refusing to load"):
        load_official_model(path, "mano")
    assert not marker.exists()


def test_garbage_file_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "generic_model.pkl"
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(OfficialModelError, match="generic_model.pkl: not a readable model pickle"):
        load_official_model(path, "flame")


def test_vertex_landmarks_are_one_hot(head: TemplateModel) -> None:
    ids = np.array([0, 17, 2561])
    faces, bary = embed_vertices(head.faces, ids)
    corners = head.faces[faces]
    np.testing.assert_array_equal(corners[np.arange(3), bary.argmax(axis=1)], ids)
    np.testing.assert_array_equal(bary.max(axis=1), 1.0)


def test_python2_module_names(hand: TemplateModel, tmp_path: Path) -> None:
    """Pickles written by Python 2 / old numpy and scipy name numpy.core and scipy.sparse.csc."""
    path = tmp_path / "MANO_RIGHT.pkl"
    write_official_pickle(hand, path)
    raw = path.read_bytes()
    assert b"numpy._core.multiarray\n" in raw and b"scipy.sparse._csc\n" in raw
    old = raw.replace(b"numpy._core.multiarray\n", b"numpy.core.multiarray\n").replace(
        b"scipy.sparse._csc\n", b"scipy.sparse.csc\n"
    )
    path.write_bytes(old)
    _assert_same_core(load_official_model(path, "mano"), hand)


def test_float32_weights_are_renormalised(hand: TemplateModel, tmp_path: Path) -> None:
    path = tmp_path / "MANO_RIGHT.pkl"
    write_official_pickle(hand, path, weights_dtype=np.float32)
    loaded = load_official_model(path, "mano")
    np.testing.assert_allclose(loaded.weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(loaded.weights, hand.weights, atol=1e-6)
