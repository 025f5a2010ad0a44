"""TemplateModel validation: every inconsistency is a ValueError naming the field."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from avatar.templates import TemplateModel


def _fields(model: TemplateModel) -> dict[str, Any]:
    return {f.name: getattr(model, f.name) for f in dataclasses.fields(model)}


def test_models_are_frozen_and_read_only(hand: TemplateModel) -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        hand.name = "flame"  # type: ignore[misc]
    with pytest.raises(ValueError):
        hand.v_template[0, 0] = 1.0


def test_kintree_root_normalised_to_minus_one(hand: TemplateModel) -> None:
    fields = _fields(hand)
    kt = np.array(hand.kintree_table).astype(np.uint32)
    kt[0, 0] = 4294967295
    fields["kintree_table"] = kt
    assert TemplateModel(**fields).kintree_table[0, 0] == -1


@pytest.mark.parametrize(
    ("field", "bad", "message"),
    [
        ("v_template", lambda m: m.v_template[:, :2], "v_template"),
        ("v_template", lambda m: np.where(np.arange(m.num_vertices)[:, None] == 3, np.nan, m.v_template), "NaN"),
        ("shapedirs", lambda m: m.shapedirs[:-1], "shapedirs"),
        ("posedirs", lambda m: m.posedirs[:, :, :-9], "posedirs"),
        ("J_regressor", lambda m: m.J_regressor[:-1], "J_regressor"),
        ("weights", lambda m: m.weights * 1.1, "sum to 1"),
        ("faces", lambda m: m.faces + m.num_vertices, "faces"),
        ("faces", lambda m: m.faces.astype(np.float64) + 0.5, "integers"),
        ("kintree_table", lambda m: m.kintree_table[:, ::-1], "parent"),
        ("inner_distance", lambda m: -np.ones(m.num_vertices), "non-negative"),
        ("hands_mean", lambda m: m.hands_mean[:-1], "hands_mean"),
        ("tip_vertex_ids", lambda m: m.tip_vertex_ids[:4], "tip_vertex_ids"),
        ("num_shape", lambda m: 11, "num_shape"),
        ("shape_roughness", lambda m: np.eye(m.num_shape + 1), "shape_roughness"),
        ("num_core_shape", lambda m: m.num_shape + 1, "num_core_shape"),
        ("shape_roughness", lambda m: np.triu(np.ones((m.num_shape, m.num_shape))), "symmetric"),
        ("name", lambda m: "smpl", "name"),
    ],
)
def test_invalid_fields_raise(hand: TemplateModel, field: str, bad: Any, message: str) -> None:
    fields = _fields(hand)
    fields[field] = bad(hand)
    with pytest.raises(ValueError, match=message):
        TemplateModel(**fields)


def test_landmark_fields_validated(head: TemplateModel) -> None:
    fields = _fields(head)
    fields["landmark_bary"] = head.landmark_bary * 2.0
    with pytest.raises(ValueError, match="landmark_bary"):
        TemplateModel(**fields)
    fields = _fields(head)
    fields["landmark_faces"] = None
    with pytest.raises(ValueError, match="together"):
        TemplateModel(**fields)
