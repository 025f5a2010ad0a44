"""Procedural hand and head: mesh validity, size, rig quality, soft tissue and blend shapes."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
import trimesh

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel, procedural_hand, procedural_head
from avatar.templates.hand import build_hand
from avatar.templates.head import build_head
from avatar.templates.meshing import triangle_quality

MIN_AREA_RATIO = 0.05  # smallest triangle area / mean area
MIN_ANGLE_DEG = 5.0


@pytest.mark.parametrize("which", ["hand", "head"])
def test_mesh_is_clean_closed_and_outward(which: str, hand: TemplateModel, head: TemplateModel) -> None:
    model = hand if which == "hand" else head
    mesh = trimesh.Trimesh(model.v_template, model.faces, process=False)
    assert np.all(np.isfinite(model.v_template))
    assert mesh.is_watertight and mesh.is_winding_consistent
    for part in mesh.split(only_watertight=False):
        assert part.volume > 0, "every component is oriented outward"
    area, min_angle = triangle_quality(model.v_template, model.faces)
    assert area.min() > MIN_AREA_RATIO * area.mean()
    assert min_angle.min() > MIN_ANGLE_DEG
    assert len(np.unique(np.sort(model.faces, axis=1), axis=0)) == len(model.faces), "no duplicate faces"


def test_sizes_and_counts(hand: TemplateModel, head: TemplateModel) -> None:
    assert 700 <= hand.num_vertices <= 2500 and 2000 <= head.num_vertices <= 6000
    joints = hand.J_regressor @ hand.v_template
    middle_tip = hand.v_template[hand.tip_vertex_ids[2]]
    assert 0.18 <= np.linalg.norm(middle_tip - joints[0]) <= 0.19
    palm = hand.v_template[hand.part_labels["palm"]]
    knuckles = palm[palm[:, 0] > 0.07]
    assert 0.08 <= np.ptp(knuckles[:, 2]) <= 0.09
    assert 0.15 <= np.ptp(head.v_template[:, 0]) <= 0.16
    chin = head.v_template[head.v_template[:, 2] > 0.05, 1].min()  # lowest point of the face
    assert 0.22 <= head.v_template[:, 1].max() - chin <= 0.24


def test_deterministic_and_cached() -> None:
    assert procedural_hand() is procedural_hand() and procedural_head() is procedural_head()
    start = time.perf_counter()
    again_hand, again_head = build_hand(), build_head()
    assert time.perf_counter() - start < 2.0, "each template builds in well under a second"
    for a, b in ((again_hand, procedural_hand()), (again_head, procedural_head())):
        for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "faces", "inner_distance"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))


def test_joint_layout(hand: TemplateModel, head: TemplateModel) -> None:
    np.testing.assert_array_equal(hand.parents, [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14])
    np.testing.assert_array_equal(head.parents, [-1, 0, 1, 1, 1])
    j = hand.J_regressor @ hand.v_template
    # Fingers point along +x from the wrist; the thumb sits on the -z side, the pinky on +z.
    assert np.all(j[[3, 6, 9, 12], 0] > j[[1, 4, 7, 10], 0])
    assert j[15, 2] < j[3, 2] < j[6, 2] < j[12, 2] < j[9, 2]
    jh = head.J_regressor @ head.v_template
    assert jh[3, 0] > 0 > jh[4, 0], "left eye (+x) is joint 3"
    assert jh[0, 1] < jh[1, 1] and jh[3, 2] > jh[2, 2]
    for model in (hand, head):
        assert np.all(model.J_regressor >= 0)
        np.testing.assert_allclose(model.J_regressor.sum(axis=1), 1.0)


def test_skinning_blends_across_joints(hand: TemplateModel) -> None:
    np.testing.assert_allclose(hand.weights.sum(axis=1), 1.0)
    assert np.all(hand.weights >= 0)
    joints = hand.J_regressor @ hand.v_template
    chains = {"index": (1, 2, 3), "middle": (4, 5, 6), "pinky": (7, 8, 9), "ring": (10, 11, 12), "thumb": (13, 14, 15)}
    for finger, (parent, joint, child) in chains.items():
        own = np.isin(np.arange(hand.num_vertices), hand.part_labels[finger])
        axis = (joints[child] - joints[parent]) / np.linalg.norm(joints[child] - joints[parent])
        s = (hand.v_template - joints[joint]) @ axis
        radial = np.linalg.norm(hand.v_template - joints[joint] - s[:, None] * axis, axis=1)
        near = own & (np.abs(s) < 0.0019) & (radial < 0.015)  # digit rings are 3.6 mm apart
        assert near.sum() >= 6
        w = hand.weights[near, joint]
        assert np.all((w > 0.15) & (w < 0.85)), "weights blend at the joint instead of stepping"
        middle = 0.5 * np.linalg.norm(joints[child] - joints[joint])
        mid_bone = own & (np.abs(s - middle) < 0.002) & (radial < 0.015)
        assert mid_bone.sum() >= 6
        assert np.all(hand.weights[mid_bone].argmax(axis=1) == joint), f"{finger}: its joint dominates mid-bone"
        assert np.all(hand.weights[mid_bone, joint] > 0.65)


def _flexion_pose(hand: TemplateModel, degrees: float) -> torch.Tensor:
    """Bend every joint of the four fingers about the axis perpendicular to its bone and the palm normal."""
    joints = hand.J_regressor @ hand.v_template
    pose = np.zeros((15, 3))
    for chain in ((1, 2, 3), (4, 5, 6), (7, 8, 9), (10, 11, 12)):
        for k, j in enumerate(chain):
            bone = joints[chain[k + 1]] - joints[j] if k < 2 else joints[j] - joints[chain[k - 1]]
            axis = np.cross(bone, [0.0, -1.0, 0.0])
            pose[j - 1] = np.radians(degrees) * axis / np.linalg.norm(axis)
    return torch.as_tensor(pose.reshape(1, 45))


@pytest.mark.parametrize("degrees", [90.0, 100.0])
def test_fist_keeps_triangles_sane(hand: TemplateModel, degrees: float) -> None:
    layer = MANOLayer(hand)
    out = layer(torch.zeros(1, 10, dtype=torch.float64), _flexion_pose(hand, degrees))
    verts = out.vertices[0].numpy()
    assert np.all(np.isfinite(verts))
    rest_area, _ = triangle_quality(hand.v_template, hand.faces)
    area, _ = triangle_quality(verts, hand.faces)
    ratio = area / rest_area
    assert 0.2 <= ratio.min() and ratio.max() <= 5.0
    rest_tips, tips = hand.v_template[hand.tip_vertex_ids[1:]], verts[hand.tip_vertex_ids[1:]]
    assert np.all(tips[:, 1] < -0.005), "curled fingertips end up on the palm side"
    assert np.all(tips[:, 0] < rest_tips[:, 0] - 0.06), "curled fingertips come back toward the wrist"


def test_pose_correctives_are_plausible(hand: TemplateModel, head: TemplateModel) -> None:
    for model in (hand, head):
        assert np.abs(model.posedirs).max() > 1e-4
    layer = MANOLayer(hand)
    pose = _flexion_pose(hand, 90.0)
    with_pd = layer(torch.zeros(1, 10, dtype=torch.float64), pose).vertices[0].numpy()
    flat = MANOLayer(hand)
    flat.posedirs.zero_()
    without = flat(torch.zeros(1, 10, dtype=torch.float64), pose).vertices[0].numpy()
    shift = np.linalg.norm(with_pd - without, axis=1)
    assert 5e-4 < shift.max() < 0.008, "knuckle correctives move the skin by millimetres"


def test_pose_basis_is_orthonormal(hand: TemplateModel) -> None:
    comps = hand.hands_components
    np.testing.assert_allclose(comps @ comps.T, np.eye(45), atol=1e-10)
    assert np.linalg.norm(hand.hands_mean) > 0


def test_shape_directions_are_plausible(hand: TemplateModel, head: TemplateModel) -> None:
    for model, n in ((hand, 10), (head, 227)):
        assert model.shapedirs.shape[2] == n
        reach = np.linalg.norm(model.shapedirs, axis=1).max(axis=0)
        assert np.all((reach > 1e-3) & (reach < 0.02)), "each direction moves the skin by mm to cm"
        flat = model.shapedirs.reshape(-1, n)
        assert np.linalg.matrix_rank(flat) == n
    assert head.num_shape == 217


def test_landmark_region_fields_move_their_landmark(head: TemplateModel) -> None:
    """Identity column 13 + 3 k + a moves landmark k along axis a (by ~1 cm per unit where no other
    landmark is near) and decays away from it: the scalp and the neck stay put."""
    layer = FLAMELayer(head, int(head.num_shape), 0)
    rest = layer.landmarks(
        layer(torch.zeros(1, head.num_shape, dtype=torch.float64), torch.zeros(1, 0, dtype=torch.float64)).vertices
    )[0].numpy()
    landmark_rows = np.einsum(
        "lk,lkvc->lvc", head.landmark_bary, head.shapedirs[head.faces[head.landmark_faces]][..., 13:217]
    )  # (68, 3, 204)
    moves = landmark_rows.reshape(68, 3, 68, 3)  # landmark, axis moved, field landmark, field axis
    own = np.einsum("kakb->kab", moves)  # (68, 3, 3): landmark k's motion under its own three fields
    assert np.all(np.abs(own - np.diagonal(own, axis1=1, axis2=2)[..., None] * np.eye(3)) < 1e-12)
    gain = np.diagonal(own, axis1=1, axis2=2)[:, 0]
    spacing = np.sort(np.linalg.norm(rest[:, None] - rest[None], axis=-1), axis=1)[:, 1]
    assert np.all(gain > 0.001) and np.all(gain <= 0.0105)
    assert np.all(gain[spacing > 0.02] > 0.008), "an isolated landmark moves by ~1 cm per unit"
    reach = np.linalg.norm(head.shapedirs[:, :, 13:217], axis=1)  # (V, 204)
    for part in ("scalp", "neck"):
        far = head.part_labels[part]
        far = far[np.linalg.norm(head.v_template[far, None] - rest[None], axis=-1).min(1) > 0.06]
        assert reach[far].max() < 1e-4, part


def test_expressions_move_the_mouth_not_the_scalp(head: TemplateModel) -> None:
    expr = np.linalg.norm(head.shapedirs[:, :, head.num_shape :], axis=1)  # (V, 10)
    mouth = head.part_labels["lips"]
    scalp = head.part_labels["scalp"]
    assert expr[mouth].mean() > 10 * expr[scalp].mean()
    smile = head.shapedirs[:, :, head.num_shape]
    corners = head.v_template[mouth]
    left = mouth[corners[:, 0] > 0.015]
    assert smile[left, 1].mean() > 0 and smile[left, 0].mean() > 0, "smile lifts the lip corners up and out"


def test_inner_distance_is_plausible(hand: TemplateModel, head: TemplateModel) -> None:
    for model in (hand, head):
        assert np.all(model.inner_distance >= 0) and np.all(np.isfinite(model.inner_distance))
    assert 0.002 < np.median(hand.inner_distance) < 0.01 and hand.inner_distance.max() < 0.03
    d, labels = head.inner_distance, head.part_labels
    forehead, chin, cheeks = (
        d[labels["forehead"]],
        d[labels["chin"]],
        d[np.r_[labels["cheek_left"], labels["cheek_right"]]],
    )
    assert 0.003 < forehead.mean() < 0.009
    assert 0.003 < chin.mean() < 0.012
    assert 0.012 < cheeks.mean() < 0.025
    assert cheeks.mean() > 1.5 * forehead.mean()


def test_part_labels(hand: TemplateModel, head: TemplateModel) -> None:
    for name in ("palm", "thumb", "index", "middle", "ring", "pinky", "palmar", "fingertips"):
        assert hand.part_labels[name].size > 0
    for name in ("face", "lips", "cheek_left", "cheek_right", "nose", "neck", "scalp", "chin", "forehead"):
        assert head.part_labels[name].size > 0
    assert np.all(head.v_template[head.part_labels["cheek_left"], 0] > 0)
    assert np.all(np.isin(head.part_labels["lips"], head.part_labels["face"]))
    # Hand digit labels partition the vertices.
    parts = np.concatenate([hand.part_labels[n] for n in ("palm", "thumb", "index", "middle", "ring", "pinky")])
    np.testing.assert_array_equal(np.sort(parts), np.arange(hand.num_vertices))


def test_head_neck_and_jaw_rig(head: TemplateModel) -> None:
    layer = FLAMELayer(head, 10, 10)
    zeros = torch.zeros(1, 10, dtype=torch.float64)
    nod = torch.tensor([[0.4, 0.0, 0.0]], dtype=torch.float64)
    rest = layer(zeros, zeros).vertices[0].numpy()
    nodded = layer(zeros, zeros, neck_pose=nod).vertices[0].numpy()
    moved = np.linalg.norm(nodded - rest, axis=1)
    assert moved[head.part_labels["scalp"]].min() > 0.01, "the neck joint carries the head"
    lowest = rest[:, 1] < rest[:, 1].min() + 0.01
    assert moved[lowest].max() < 1e-3, "the neck base stays with the global joint"
    jaw = layer(zeros, zeros, jaw_pose=nod).vertices[0].numpy()
    moved = np.linalg.norm(jaw - rest, axis=1)
    assert moved[head.part_labels["chin"]].min() > 0.01 and moved[head.part_labels["forehead"]].max() < 1e-9
