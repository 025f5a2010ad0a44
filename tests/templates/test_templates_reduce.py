"""The keypoint-only template gives the same keypoints as the full one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel
from avatar.templates.reduce import keypoint_template


def test_reduced_mano_matches_full(hand: TemplateModel) -> None:
    reduced = keypoint_template(hand)
    assert reduced.num_vertices == 5 + hand.num_joints < hand.num_vertices // 50
    full, small = MANOLayer(hand), MANOLayer(reduced)
    rng = np.random.default_rng(0)
    args = [torch.as_tensor(rng.normal(0, s, (4, w))) for s, w in ((1.0, 10), (0.6, 45), (1.0, 3), (0.1, 3))]
    a, b = full(*args), small(*args)
    torch.testing.assert_close(b.joints, a.joints, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        small.keypoints21(b.vertices, b.joints), full.keypoints21(a.vertices, a.joints), rtol=0, atol=1e-12
    )


def test_reduced_flame_matches_full(head: TemplateModel) -> None:
    reduced = keypoint_template(head)
    assert reduced.num_vertices < head.num_vertices // 4
    n_shape, n_expr = int(head.num_shape), head.num_shapes_total - int(head.num_shape)
    full, small = FLAMELayer(head, n_shape, n_expr), FLAMELayer(reduced, n_shape, n_expr)
    rng = np.random.default_rng(1)
    args = [
        torch.as_tensor(rng.normal(0, s, (3, w)))
        for s, w in ((1.0, n_shape), (1.0, n_expr), (0.3, 3), (0.2, 3), (0.2, 3), (0.1, 6), (0.1, 3))
    ]
    a, b = full(*args), small(*args)
    torch.testing.assert_close(b.joints, a.joints, rtol=0, atol=1e-12)
    torch.testing.assert_close(small.landmarks(b.vertices), full.landmarks(a.vertices), rtol=0, atol=1e-12)


def test_template_without_keypoints_is_refused(hand: TemplateModel) -> None:
    bare = dataclasses.replace(hand, tip_vertex_ids=None)
    with pytest.raises(ValueError, match="no keypoints"):
        keypoint_template(bare)
