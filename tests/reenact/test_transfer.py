"""Motion transfer against closed forms: identity when driving oneself, the hand-to-head transform kept (its
translation scaled by the head sizes, its rotation in the hands' anatomical frames), the target's shape and place
kept, a touch kept on the same surface point of another face, bad drivers refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.geometry.winding import winding_number
from avatar.posing import pose_layers
from avatar.reenact import MotionTransferError, head_size, transfer_motion
from avatar.reenact.contact import surface_twins, twin_points
from avatar.synthetic.geometry import closest_points, vertex_normals
from avatar.templates import procedural_hand, procedural_head
from avatar.templates.layers import hand_frame
from avatar.templates.lbs import batch_rodrigues

HEAD, HAND = procedural_head(), procedural_hand()


def _params(seed: int, frames: int = 4, shape_scale: float = 1.0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = lambda *shape, s=0.1: rng.normal(0, s, shape)  # noqa: E731
    return {
        "flame_shape": np.repeat(n(1, 10, s=shape_scale), frames, 0),
        "flame_expression": n(frames, 10, s=0.5),
        "flame_global_orient": n(frames, 3),
        "flame_neck_pose": n(frames, 3),
        "flame_jaw_pose": n(frames, 3, s=0.05),
        "flame_eye_pose": n(frames, 6, s=0.05),
        "flame_transl": n(frames, 3, s=0.02) + [0.0, 0.0, 0.5],
        "mano_shape": np.repeat(n(1, 10, s=shape_scale), frames, 0),
        "mano_hand_pose": n(frames, 45, s=0.2),
        "mano_global_orient": n(frames, 3, s=0.5),
        "mano_transl": n(frames, 3, s=0.02) + [0.05, -0.02, 0.45],
    }


def _relative(params: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_rel (T, 3, 3), t_rel (T, 3) in the head frame, head roots (T, 3)) of posed parameters."""
    _, face, _, hand = pose_layers(params, HEAD, HAND, torch.float64)
    R_head = batch_rodrigues(torch.from_numpy(np.asarray(params["flame_global_orient"], np.float64))).numpy()
    R_hand = batch_rodrigues(torch.from_numpy(np.asarray(params["mano_global_orient"], np.float64))).numpy()
    root, wrist = face.joints[:, 0].numpy(), hand.joints[:, 0].numpy()
    return np.swapaxes(R_head, 1, 2) @ R_hand, np.einsum("tji,tj->ti", R_head, wrist - root), root


def _rest_frame(params: dict[str, np.ndarray]) -> np.ndarray:
    """(3, 3) anatomical frame of the hand shape of ``params`` in its rest pose."""
    rest = {
        **{k: v[:1] for k, v in params.items()},
        "mano_hand_pose": np.zeros((1, 45)),
        "mano_global_orient": np.zeros((1, 3)),
        "mano_transl": np.zeros((1, 3)),
    }
    return hand_frame(pose_layers(rest, HEAD, HAND, torch.float64)[3].joints[0].numpy())


@pytest.mark.filterwarnings("ignore:motion transfer")  # random hands may lie inside the face
@pytest.mark.parametrize("placement", ["contact", "scaled"])
def test_driving_oneself_changes_nothing(placement: str):
    params = _params(0)
    out, scale, _ = transfer_motion(params, params, HEAD, HAND, placement)
    assert scale == pytest.approx(1.0)
    for key, value in params.items():
        np.testing.assert_allclose(out[key], value, atol=1e-9, err_msg=key)


def test_hands_of_one_shape_keep_the_driver_s_mano_rotations():
    target, driver = _params(1, frames=3), _params(2, frames=5)
    driver["mano_shape"] = target["mano_shape"][:1].repeat(5, 0)
    out, _, _ = transfer_motion(target, driver, HEAD, HAND, "scaled")
    np.testing.assert_allclose(out["mano_hand_pose"], driver["mano_hand_pose"], atol=1e-12)
    np.testing.assert_allclose(_relative(out)[0], _relative(driver)[0], atol=1e-9)


def test_another_actor_keeps_its_shape_and_place_and_the_driver_s_hand_to_head_transform():
    target, driver = _params(1, frames=3, shape_scale=2.0), _params(2, frames=5, shape_scale=2.0)
    out, scale, frames = transfer_motion(target, driver, HEAD, HAND, "scaled")
    assert len(out["flame_global_orient"]) == 5 and frames == []
    np.testing.assert_allclose(out["flame_shape"], np.repeat(target["flame_shape"][:1], 5, 0))
    np.testing.assert_allclose(out["mano_shape"], np.repeat(target["mano_shape"][:1], 5, 0))
    for key in ("flame_expression", "flame_jaw_pose", "flame_global_orient"):
        np.testing.assert_array_equal(out[key], driver[key])
    R_out, t_out, root_out = _relative(out)
    R_drv, t_drv, root_drv = _relative(driver)
    # the hand's anatomical frame relative to the head, and each finger's rotation in it
    change = _rest_frame(out) @ _rest_frame(driver).T
    assert not np.allclose(change, np.eye(3), atol=1e-3)  # the two hand shapes' frames differ
    np.testing.assert_allclose(R_out @ _rest_frame(out), R_drv @ _rest_frame(driver), atol=1e-9)
    np.testing.assert_allclose(
        out["mano_hand_pose"].reshape(5, 15, 3), driver["mano_hand_pose"].reshape(5, 15, 3) @ change.T, atol=1e-12
    )
    np.testing.assert_allclose(t_out, scale * t_drv, atol=1e-9)  # its offset, scaled by the head sizes
    np.testing.assert_allclose(root_out[0], _relative(target)[2][0], atol=1e-9)  # the target stays in place
    np.testing.assert_allclose(root_out - root_out[0], root_drv - root_drv[0], atol=1e-9)  # moving as the driver
    sizes = [
        head_size(pose_layers({k: v[:1] for k, v in p.items()}, HEAD, HAND, torch.float64)[1].vertices[0].numpy())
        for p in (target, driver)
    ]
    assert scale == pytest.approx(sizes[0] / sizes[1]) and abs(scale - 1.0) > 1e-3


def test_head_size_is_rotation_invariant_and_scales_linearly():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(50, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    assert head_size(points @ q.T + 5.0) == pytest.approx(head_size(points))
    assert head_size(2.5 * points) == pytest.approx(2.5 * head_size(points))


def _inside_depth(hand: np.ndarray, face: np.ndarray) -> float:
    """Deepest hand vertex (Vh, 3) inside the closed face mesh (V, 3), metres (0 when none is)."""
    faces, face_t = torch.from_numpy(np.array(HEAD.faces)), torch.from_numpy(face)
    distance = closest_points(torch.from_numpy(hand), face_t, faces)[1]
    near = torch.nonzero(distance < 0.02).squeeze(1)  # the hand is thinner than 4 cm
    inside = winding_number(torch.from_numpy(hand)[near], face_t, faces) > 0.5
    return float(distance[near][inside].max()) if inside.any() else 0.0


def _touching(params: dict[str, np.ndarray], offset: float) -> dict[str, np.ndarray]:
    """``params`` with straight fingers pointing at the left cheek, moved along the cheek's normal until the hand's
    nearest vertex lies ``offset`` metres outside the face (negative: the fingertip that far inside)."""
    out = {k: v.copy() for k, v in params.items()}
    out["mano_hand_pose"][:] = 0.0
    face = pose_layers(out, HEAD, HAND, torch.float64)[1].vertices.numpy()
    cheek = np.asarray(HEAD.part_labels["cheek_left"])
    cheek = int(cheek[np.argmin(np.linalg.norm(face[0, cheek] - face[0, cheek].mean(0), axis=1))])
    faces = torch.from_numpy(np.array(HEAD.faces))
    normals = [vertex_normals(torch.from_numpy(f), faces).numpy()[cheek] for f in face]
    finger = _rest_frame(out)[:, 0]
    for t, normal in enumerate(normals):
        axis = np.cross(finger, -normal)
        out["mano_global_orient"][t] = axis / np.linalg.norm(axis) * np.arctan2(np.linalg.norm(axis), finger @ -normal)
    out["mano_transl"][:] = 0.0
    hand = pose_layers(out, HEAD, HAND, torch.float64)[3].vertices.numpy()
    for t, normal in enumerate(normals):
        out["mano_transl"][t] = face[t, cheek] - hand[t, np.argmax(hand[t] @ -normal)]
        for _ in range(20):  # slide out along the normal until nothing is inside, then set the gap
            moved = hand[t] + out["mano_transl"][t]
            gap = closest_points(torch.from_numpy(moved), torch.from_numpy(face[t]), faces)[1].min().item()
            depth = _inside_depth(moved, face[t])
            step = depth + 1e-4 if depth > 0 else offset - gap if offset >= 0 else 0.0
            out["mano_transl"][t] += step * normal
            if abs(step) < 1e-6:
                break
        if offset < 0:
            out["mano_transl"][t] += offset * normal
    return out


def _hand_and_face(params: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    _, face, _, hand = pose_layers(params, HEAD, HAND, torch.float64)
    return hand.vertices.numpy(), face.vertices.numpy()


def test_a_fingertip_on_the_cheek_lands_on_the_other_actor_s_cheek():
    """Stated tolerance: the driver's touching fingertip (1 mm from its cheek) within 1.5 mm of its point on the
    target's cheek, and no hand vertex deeper inside the target's face than 0.5 mm (the driver's: none)."""
    target, driver = _params(7, frames=2), _touching(_params(8, frames=2), 0.001)
    target["flame_shape"][:, 0] += 1.5  # a larger head
    faces = np.array(HEAD.faces)
    d_hand, d_face = _hand_and_face(driver)
    scaled = transfer_motion(target, driver, HEAD, HAND, "scaled")
    kept = transfer_motion(target, driver, HEAD, HAND, "contact")
    assert abs(kept.head_scale - 1.0) > 0.01
    for t in range(2):
        assert _inside_depth(d_hand[t], d_face[t]) == 0.0
        twins = surface_twins(d_hand[t], d_face[t], faces)
        tip = int(np.argmin(twins.distance))
        assert twins.distance[tip] == pytest.approx(0.001, abs=1e-5)
        misses = {}
        for name, result in (("contact", kept), ("scaled", scaled)):
            hand, face = _hand_and_face(result.params)
            goal = twin_points(surface_twins(d_hand[t, [tip]], d_face[t], faces), face[t], faces)[0]
            misses[name] = np.linalg.norm(hand[t, tip] - goal)
            if name == "contact":
                assert _inside_depth(hand[t], face[t]) < 5e-4
        assert misses["contact"] < 1.5e-3 and misses["scaled"] > 2 * misses["contact"]
        assert kept.frames[t]["touching_points"] >= 1 and kept.frames[t]["residual_mm"] < 1.5


def test_a_frame_without_contact_transfers_exactly_as_the_scaled_transform():
    target, driver = _params(7, frames=2, shape_scale=2.0), _touching(_params(8, frames=2, shape_scale=2.0), 0.08)
    kept = transfer_motion(target, driver, HEAD, HAND, "contact")
    scaled = transfer_motion(target, driver, HEAD, HAND, "scaled")
    for key, value in scaled.params.items():
        np.testing.assert_array_equal(kept.params[key], value, err_msg=key)
    assert all(f["matched_points"] == 0 and f["moved_mm"] == 0.0 for f in kept.frames)


def test_a_hand_through_the_driver_s_own_face_warns_once_and_transfers():
    target, driver = _params(7, frames=2), _touching(_params(8, frames=2), -0.03)
    with pytest.warns(UserWarning, match="inside the driver's own face") as caught:
        result = transfer_motion(target, driver, HEAD, HAND, "contact")
    assert len(caught) == 1 and np.isfinite(result.params["mano_transl"]).all()


def test_bad_drivers_are_refused_with_the_reason():
    target = _params(4)
    with pytest.raises(MotionTransferError, match="no frames"):
        transfer_motion(target, {k: v[:0] for k, v in target.items()}, HEAD, HAND)
    broken = _params(5)
    broken["mano_hand_pose"][2, 7] = np.nan
    with pytest.raises(MotionTransferError, match=r"'mano_hand_pose' is not finite in frames \[2\]"):
        transfer_motion(target, broken, HEAD, HAND)
    other = _params(6)
    other["flame_expression"] = np.zeros((4, 50))
    with pytest.raises(MotionTransferError, match="different templates"):
        transfer_motion(target, other, HEAD, HAND)


def test_a_driver_far_beyond_any_capture_is_refused_with_the_cause_and_the_fix(tmp_path):
    """A head 1e30 m away is finite but collapses to a point when posed: the transfer names the column and the
    frames, and ``reenact.driver=`` names the file before any stage runs."""
    from avatar.artifacts import write_params
    from avatar.reenact.driving import driver_file_problem

    absurd = _params(5)
    absurd["flame_transl"][1:3] = 1e30
    with pytest.raises(MotionTransferError, match=r"'flame_transl' reaches 1e\+30 m in frames \[1, 2\]"):
        transfer_motion(_params(4), absurd, HEAD, HAND)
    path = tmp_path / "params.parquet"
    write_params(path, absurd)
    problem = driver_file_problem(str(path))
    assert problem is not None and problem.startswith(f"reenact.driver={path}: the driver's 'flame_transl'"), problem
    assert "fix or drop those frames' parameters" in problem
