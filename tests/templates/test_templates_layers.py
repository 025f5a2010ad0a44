"""MANO / FLAME layer specifics: PCA pose, mean pose, keypoints, landmarks, input checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel


def _zeros(*shape: int) -> torch.Tensor:
    return torch.zeros(*shape, dtype=torch.float64)


def test_pca_pose_equals_full_pose(hand: TemplateModel) -> None:
    rng = np.random.default_rng(0)
    coeffs = torch.as_tensor(rng.normal(0, 1.0, (2, 12)))
    betas = torch.as_tensor(rng.normal(0, 1.0, (2, 10)))
    pca = MANOLayer(hand, use_pca=True, num_pca_comps=12)
    full = MANOLayer(hand)
    pose = coeffs @ torch.as_tensor(np.array(hand.hands_components[:12]))
    np.testing.assert_allclose(pca(betas, coeffs).vertices.numpy(), full(betas, pose).vertices.numpy(), atol=1e-12)
    relaxed = MANOLayer(hand, flat_hand_mean=False)
    np.testing.assert_allclose(
        relaxed(betas, _zeros(2, 45)).vertices.numpy(),
        full(betas, torch.as_tensor(np.tile(hand.hands_mean, (2, 1)))).vertices.numpy(),
        atol=1e-12,
    )


def test_keypoints21_openpose_order(hand: TemplateModel) -> None:
    layer = MANOLayer(hand)
    out = layer(_zeros(1, 10), _zeros(1, 45))
    kp = layer.keypoints21(out.vertices, out.joints)[0].numpy()
    joints, verts = out.joints[0].numpy(), out.vertices[0].numpy()
    assert kp.shape == (21, 3)
    np.testing.assert_allclose(kp[0], joints[0])
    chains = {"thumb": (13, 14, 15), "index": (1, 2, 3), "middle": (4, 5, 6), "ring": (10, 11, 12), "pinky": (7, 8, 9)}
    for finger, (name, chain) in enumerate(chains.items()):
        block = kp[1 + 4 * finger : 5 + 4 * finger]
        np.testing.assert_allclose(block[:3], joints[list(chain)])
        np.testing.assert_allclose(block[3], verts[hand.tip_vertex_ids[finger]])
        dist = np.linalg.norm(block - kp[0], axis=1)
        assert np.all(np.diff(dist) > 0), f"{name} keypoints must move away from the wrist"


def test_flame_landmarks_follow_the_mesh(head: TemplateModel) -> None:
    layer = FLAMELayer(head, 10, 10)
    jaw = _zeros(1, 3)
    jaw[0, 0] = 0.3
    rest = layer.landmarks(layer(_zeros(1, 10), _zeros(1, 10)).vertices)[0].numpy()
    opened = layer.landmarks(layer(_zeros(1, 10), _zeros(1, 10), jaw_pose=jaw).vertices)[0].numpy()
    assert rest.shape == (68, 3)
    assert rest[36, 0] < 0 < rest[45, 0], "iBUG order: subject's right eye first"
    assert np.argmax(rest[:, 2]) in (30, 33), "nose tip is the most forward landmark"
    gap_rest, gap_open = (np.linalg.norm(lm[51] - lm[57]) for lm in (rest, opened))
    assert gap_open > gap_rest + 0.015, "opening the jaw opens the lips"
    assert opened[8, 1] < rest[8, 1] - 0.015, "the chin drops"
    np.testing.assert_allclose(opened[36:48], rest[36:48], atol=1e-12)  # eyes do not move with the jaw


def test_eye_pose_moves_only_the_eyes(head: TemplateModel) -> None:
    layer = FLAMELayer(head, 10, 10)
    eyes = _zeros(1, 6)
    eyes[0, 1] = 0.4  # left eye yaw
    rest = layer(_zeros(1, 10), _zeros(1, 10)).vertices[0].numpy()
    moved = layer(_zeros(1, 10), _zeros(1, 10), eye_pose=eyes).vertices[0].numpy()
    changed = np.flatnonzero(np.linalg.norm(moved - rest, axis=1) > 1e-9)
    eye_centre = (head.J_regressor @ head.v_template)[3]
    assert changed.size > 0
    assert np.all(np.linalg.norm(rest[changed] - eye_centre, axis=1) < 0.03), "only the left eye region moves"


def test_layer_input_errors(hand: TemplateModel, head: TemplateModel) -> None:
    layer = MANOLayer(hand)
    with pytest.raises(ValueError, match="hand_pose"):
        layer(_zeros(1, 10), _zeros(1, 44))
    with pytest.raises(ValueError, match="betas"):
        layer(_zeros(1, 9), _zeros(1, 45))
    with pytest.raises(ValueError, match="num_pca_comps"):
        MANOLayer(hand, use_pca=True, num_pca_comps=46)
    with pytest.raises(ValueError, match="mano"):
        MANOLayer(head)
    with pytest.raises(ValueError, match="num_expression"):
        FLAMELayer(head, 10, 11)
    with pytest.raises(ValueError, match="eye_pose"):
        FLAMELayer(head, 10, 10)(_zeros(1, 10), _zeros(1, 10), eye_pose=_zeros(1, 3))


def test_flame_layer_column_selection(head: TemplateModel) -> None:
    """FLAMELayer(num_shape=k, num_expression=m) uses the first k shape and first m expression columns."""
    small = FLAMELayer(head, 3, 2)
    full = FLAMELayer(head, 10, 10)
    rng = np.random.default_rng(1)
    shape, expr = torch.as_tensor(rng.normal(size=(1, 3))), torch.as_tensor(rng.normal(size=(1, 2)))
    padded = full(torch.cat((shape, _zeros(1, 7)), 1), torch.cat((expr, _zeros(1, 8)), 1))
    np.testing.assert_allclose(small(shape, expr).vertices.numpy(), padded.vertices.numpy(), atol=1e-12)


def test_flame_layer_for_params_takes_the_widths_of_the_table(head: TemplateModel) -> None:
    """A table with fewer shape columns than the template (a synthetic subject's 10) poses as zero-padded."""
    rng = np.random.default_rng(7)
    narrow = {"flame_shape": rng.normal(0, 1, (2, 10)), "flame_expression": rng.normal(0, 1, (2, 4))}
    layer = FLAMELayer.for_params(head, narrow)
    assert (layer.num_shape, layer.num_expression) == (10, 4)
    full = FLAMELayer(head, int(head.num_shape), 4)
    padded = np.concatenate((narrow["flame_shape"], np.zeros((2, int(head.num_shape) - 10))), axis=1)
    a = layer(torch.as_tensor(narrow["flame_shape"]), torch.as_tensor(narrow["flame_expression"])).vertices
    b = full(torch.as_tensor(padded), torch.as_tensor(narrow["flame_expression"])).vertices
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-12)
    too_wide = {"flame_shape": np.zeros((1, int(head.num_shape) + 1)), "flame_expression": np.zeros((1, 10))}
    with pytest.raises(ValueError, match="num_shape must lie in"):
        FLAMELayer.for_params(head, too_wide)
