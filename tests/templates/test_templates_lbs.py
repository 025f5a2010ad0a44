"""LBS and the layers against an independent brute-force reference (numpy loops + scipy rotations)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from avatar.templates import FLAMELayer, MANOLayer, TemplateModel, batch_rodrigues, lbs


def reference_lbs(model: TemplateModel, betas: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex, per-joint loop implementation of SMPL-style skinning (no translation)."""
    V, J = model.num_vertices, model.num_joints
    v_shaped = np.empty((V, 3))
    for i in range(V):
        v_shaped[i] = model.v_template[i] + model.shapedirs[i, :, : betas.size] @ betas
    joints = model.J_regressor @ v_shaped
    rots = [Rotation.from_rotvec(p).as_matrix() for p in pose]
    feature = np.concatenate([(rots[j] - np.eye(3)).ravel() for j in range(1, J)])
    world = []
    for j in range(J):
        local = np.eye(4)
        local[:3, :3] = rots[j]
        parent = int(model.kintree_table[0, j])
        local[:3, 3] = joints[j] - (joints[parent] if parent >= 0 else 0.0)
        world.append(local if parent < 0 else world[parent] @ local)
    out = np.zeros((V, 3))
    for i in range(V):
        v_posed = v_shaped[i] + model.posedirs[i] @ feature
        for j in range(J):
            w = model.weights[i, j]
            if w:
                out[i] += w * (world[j][:3, :3] @ (v_posed - joints[j]) + world[j][:3, 3])
    return out, np.stack([g[:3, 3] for g in world])


def _t(a: np.ndarray, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _random_hand_inputs(rng: np.random.Generator, batch: int = 1) -> dict[str, np.ndarray]:
    return {
        "betas": rng.normal(0, 1.0, (batch, 10)),
        "hand_pose": rng.normal(0, 0.4, (batch, 45)),
        "global_orient": rng.normal(0, 0.5, (batch, 3)),
        "transl": rng.normal(0, 0.1, (batch, 3)),
    }


def _random_head_inputs(rng: np.random.Generator, batch: int = 1, num_shape: int = 10) -> dict[str, np.ndarray]:
    return {
        "shape": rng.normal(0, 1.0, (batch, num_shape)),
        "expression": rng.normal(0, 1.0, (batch, 10)),
        "global_orient": rng.normal(0, 0.3, (batch, 3)),
        "neck_pose": rng.normal(0, 0.3, (batch, 3)),
        "jaw_pose": np.abs(rng.normal(0, 0.2, (batch, 3))),
        "eye_pose": rng.normal(0, 0.2, (batch, 6)),
        "transl": rng.normal(0, 0.1, (batch, 3)),
    }


def test_batch_rodrigues_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    rotvecs = np.concatenate(
        [
            rng.normal(0, 1.5, (50, 3)),
            rng.normal(0, 1e-9, (5, 3)),
            np.zeros((1, 3)),
            np.array([[np.pi - 1e-6, 0, 0], [0, 0, 3 * np.pi / 2]]),
            rng.normal(0, 5e-3, (5, 3)),
        ]
    )
    got = batch_rodrigues(_t(rotvecs)).numpy()
    np.testing.assert_allclose(got, Rotation.from_rotvec(rotvecs).as_matrix(), atol=1e-12)


def test_batch_rodrigues_gradient_finite_at_exact_zero() -> None:
    r = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    rot = batch_rodrigues(r)
    (rot * torch.arange(36, dtype=torch.float64).reshape(4, 3, 3)).sum().backward()
    assert torch.isfinite(r.grad).all()
    # d R / d r at 0 is the skew generator: d/dr_x of R[2, 1] == 1.
    r2 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    batch_rodrigues(r2)[2, 1].backward()
    np.testing.assert_allclose(r2.grad.numpy(), [1.0, 0.0, 0.0], atol=1e-12)


def test_mano_layer_matches_brute_force(hand: TemplateModel) -> None:
    rng = np.random.default_rng(1)
    layer = MANOLayer(hand)
    for _ in range(2):
        x = _random_hand_inputs(rng)
        out = layer(**{k: _t(v) for k, v in x.items()})
        pose = np.concatenate([x["global_orient"], x["hand_pose"]], axis=1).reshape(16, 3)
        ref_v, ref_j = reference_lbs(hand, x["betas"][0], pose)
        np.testing.assert_allclose(out.vertices[0].numpy(), ref_v + x["transl"], atol=1e-10)
        np.testing.assert_allclose(out.joints[0].numpy(), ref_j + x["transl"], atol=1e-10)


def test_flame_layer_matches_brute_force(head: TemplateModel) -> None:
    rng = np.random.default_rng(2)
    layer = FLAMELayer(head, num_shape=int(head.num_shape), num_expression=10)  # every shapedirs column
    x = _random_head_inputs(rng, num_shape=int(head.num_shape))
    out = layer(**{k: _t(v) for k, v in x.items()})
    pose = np.concatenate([x["global_orient"], x["neck_pose"], x["jaw_pose"], x["eye_pose"]], axis=1).reshape(5, 3)
    ref_v, ref_j = reference_lbs(head, np.concatenate([x["shape"][0], x["expression"][0]]), pose)
    np.testing.assert_allclose(out.vertices[0].numpy(), ref_v + x["transl"], atol=1e-10)
    np.testing.assert_allclose(out.joints[0].numpy(), ref_j + x["transl"], atol=1e-10)


@pytest.mark.parametrize("which", ["hand", "head"])
def test_rest_joints_equal_regressed_template(which: str, hand: TemplateModel, head: TemplateModel) -> None:
    model = hand if which == "hand" else head
    if which == "hand":
        out = MANOLayer(model)(torch.zeros(1, 10, dtype=torch.float64), torch.zeros(1, 45, dtype=torch.float64))
    else:
        zeros = torch.zeros(1, 10, dtype=torch.float64)
        out = FLAMELayer(model, 10, 10)(zeros, zeros)
    np.testing.assert_allclose(out.joints[0].numpy(), model.J_regressor @ model.v_template, atol=1e-12)
    np.testing.assert_allclose(out.vertices[0].numpy(), model.v_template, atol=1e-12)


def test_root_rotation_rotates_about_root_joint(hand: TemplateModel, head: TemplateModel) -> None:
    rng = np.random.default_rng(3)
    rotvec = np.array([0.3, -1.1, 0.7])
    rot = Rotation.from_rotvec(rotvec).as_matrix()
    x = _random_hand_inputs(rng)
    layer = MANOLayer(hand)
    base = layer(_t(x["betas"]), _t(x["hand_pose"]))
    turned = layer(_t(x["betas"]), _t(x["hand_pose"]), global_orient=_t(rotvec[None]))
    v0, j0 = base.vertices[0].numpy(), base.joints[0, 0].numpy()
    np.testing.assert_allclose(turned.vertices[0].numpy(), (v0 - j0) @ rot.T + j0, atol=1e-12)
    y = _random_head_inputs(rng)
    flame = FLAMELayer(head, 10, 10)
    kwargs = {k: _t(v) for k, v in y.items() if k not in ("global_orient", "transl")}
    base = flame(**kwargs)
    turned = flame(**kwargs, global_orient=_t(rotvec[None]))
    v0, j0 = base.vertices[0].numpy(), base.joints[0, 0].numpy()
    np.testing.assert_allclose(turned.vertices[0].numpy(), (v0 - j0) @ rot.T + j0, atol=1e-12)


def test_float32_and_float64_agree(hand: TemplateModel, head: TemplateModel) -> None:
    rng = np.random.default_rng(4)
    x = _random_hand_inputs(rng, batch=3)
    layer = MANOLayer(hand)
    out64 = layer(**{k: _t(v) for k, v in x.items()})
    out32 = layer(**{k: _t(v, torch.float32) for k, v in x.items()})
    assert out32.vertices.dtype == torch.float32 and out64.vertices.dtype == torch.float64
    scale = out64.vertices.abs().max().item()
    assert (out32.vertices.double() - out64.vertices).abs().max().item() <= 1e-5 * scale
    y = _random_head_inputs(rng, batch=2)
    flame = FLAMELayer(head, 10, 10)
    f64 = flame(**{k: _t(v) for k, v in y.items()})
    f32 = flame(**{k: _t(v, torch.float32) for k, v in y.items()})
    assert (f32.vertices.double() - f64.vertices).abs().max().item() <= 1e-5 * f64.vertices.abs().max().item()


def test_mano_layer_gradcheck(hand: TemplateModel) -> None:
    rng = np.random.default_rng(5)
    layer = MANOLayer(hand)
    x = {k: _t(v).requires_grad_(True) for k, v in _random_hand_inputs(rng).items()}
    # Include exactly-zero rotations: the gradient must stay exact there too.
    with torch.no_grad():
        x["hand_pose"][0, :9] = 0.0

    def fn(betas, hand_pose, global_orient, transl):  # type: ignore[no-untyped-def]
        out = layer(betas, hand_pose, global_orient, transl)
        return out.joints, out.vertices[:, ::37]

    assert torch.autograd.gradcheck(fn, tuple(x.values()), eps=1e-6, atol=1e-6, fast_mode=True)


def test_gradient_finite_at_zero_pose(head: TemplateModel) -> None:
    flame = FLAMELayer(head, 10, 10)
    inputs = {
        k: torch.zeros(2, n, dtype=torch.float64, requires_grad=True)
        for k, n in (
            ("shape", 10),
            ("expression", 10),
            ("global_orient", 3),
            ("neck_pose", 3),
            ("jaw_pose", 3),
            ("eye_pose", 6),
            ("transl", 3),
        )
    }
    flame(**inputs).vertices.square().sum().backward()
    assert all(torch.isfinite(t.grad).all() for t in inputs.values())


def test_lbs_accepts_rotation_matrices(head: TemplateModel) -> None:
    rng = np.random.default_rng(6)
    pose = _t(rng.normal(0, 0.3, (2, 5, 3)))
    betas = _t(rng.normal(0, 1.0, (2, head.num_shapes_total)))
    arrays = [_t(np.array(getattr(head, k))) for k in ("v_template", "shapedirs", "posedirs", "J_regressor")]
    parents, weights = [int(p) for p in head.parents], _t(np.array(head.weights))
    from_rotvec = lbs(betas, pose, *arrays, parents, weights)
    from_matrix = lbs(betas, batch_rodrigues(pose), *arrays, parents, weights)
    for a, b in zip(from_rotvec, from_matrix):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-14)
