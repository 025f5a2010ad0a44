"""The dynamic model: zero-initialised heads, the interaction weight and gating, conditioning, extremes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch import nn

from avatar.dynamic import sequence_conditioning
from avatar.nets.encoding import encoded_dim, positional_encoding
from avatar.nets.mlp import DeltaMLP
from avatar.posing import pose_layers
from avatar.representations.bound.dynamic_model import (
    DynamicModelConfig,
    interaction_weights,
    nearest_distance,
    sample_one_per_triangle,
)
from avatar.representations.bound.gaussians import SH_C0
from avatar.representations.bound.warmup import render_frame
from avatar.templates import procedural_hand, procedural_head
from avatar.training.rendering import rasterize
from tests.representations.bound.conftest import FAR, NEAR, TINY, Scene, make_scene, scene_params


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_zero_initialised_heads_render_the_warmup_model_exactly(scene: Scene, backend: str) -> None:
    from avatar.render.gaussians import resolve_backend

    if backend == "cpu" and resolve_backend("auto", torch.zeros(1)) != "cpu":
        pytest.skip("compiled rasterizer not built")
    model = scene.model()
    for frame in (NEAR, FAR):
        with torch.no_grad():
            static, _ = render_frame(model.gaussians, scene.meshes, scene.views, frame, 0, backend)
            g = model(scene.cond.frame(frame), scene.meshes.vertices[frame])
            dynamic = rasterize(g, scene.views, 0, backend)
        assert torch.equal(static.rgb, dynamic.rgb)
        assert torch.equal(static.alpha, dynamic.alpha)


def test_interaction_weight_closed_form() -> None:
    d = torch.tensor([0.0, 0.0125, 0.025, 0.05, 0.07, math.inf])
    w = interaction_weights(d, 0.05)
    expected = torch.tensor([1.0, (math.cos(math.pi / 4) + 1) / 2, 0.5, 0.0, 0.0, 0.0])
    torch.testing.assert_close(w, expected)
    dense = interaction_weights(torch.linspace(0, 0.06, 200), 0.05)
    assert (dense.diff() <= 1e-7).all()  # non-increasing


def test_nearest_distance_against_brute_force() -> None:
    gen = torch.Generator().manual_seed(0)
    points, targets = torch.rand(500, 3, generator=gen), torch.rand(40, 3, generator=gen) * 0.3
    d = nearest_distance(points, targets, reach=0.05)
    brute = torch.cdist(points, targets).min(-1).values
    near = brute < 0.05
    torch.testing.assert_close(d[near], brute[near])
    assert (d[~near] >= 0.05 - 1e-7).all()
    assert nearest_distance(points, targets[:0], 0.05).isinf().all()


def test_interaction_runs_only_near_the_hand(scene: Scene) -> None:
    model = scene.model()
    with torch.no_grad():
        near = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
        far = model(scene.cond.frame(FAR), scene.meshes.vertices[FAR])
    assert near.interaction_evaluations > 0
    assert far.interaction_evaluations == 0  # the hand a metre away costs nothing


def test_interaction_module_is_not_called_without_a_hand_nearby(scene: Scene, monkeypatch) -> None:
    model = scene.model()
    calls = []
    monkeypatch.setattr(model.interaction, "forward", lambda *a: calls.append(1) or {})
    with torch.no_grad():
        model(scene.cond.frame(FAR), scene.meshes.vertices[FAR])
    assert calls == []


def test_deltas_weighted_by_w_and_only_on_the_right_parts(scene: Scene) -> None:
    """With non-zero output layers, hand deltas move only hand Gaussians, interaction deltas only face
    Gaussians within d_max, scaled by w (a Gaussian at w = 0 does not move)."""
    model = scene.model()
    with torch.no_grad():
        base = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
        for heads in (model.hand_geo, model.interaction):
            for head in heads.heads.values():
                head.output.bias.fill_(0.05)
        moved = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
    changed = (moved.local_means - base.local_means).abs().sum(-1) > 0
    hand = model.gaussians.part == model.hand_part
    assert changed[hand].all()
    face_changed = changed & ~hand
    assert 0 < face_changed.sum() == moved.interaction_evaluations
    # the delta is w * 0.05 per axis: recover w and compare with the closed form
    face = model.face_index
    w = (moved.local_means - base.local_means)[face, 0] / 0.05
    with torch.no_grad():
        means, _, _ = model.gaussians.world(scene.meshes.vertices[NEAR], model.faces)
        d = nearest_distance(means[face], scene.meshes.vertices[NEAR, scene.num_face_vertices :], 0.05)
    torch.testing.assert_close(w, interaction_weights(d, 0.05), atol=1e-5, rtol=1e-4)


def test_positional_encoding_closed_form() -> None:
    x = torch.tensor([[0.25, -0.5, 1.0]])
    out = positional_encoding(x, 2)
    assert out.shape == (1, encoded_dim(3, 2)) == (1, 15)
    expected = torch.cat(
        [x, torch.sin(math.pi * x), torch.cos(math.pi * x), torch.sin(2 * math.pi * x), torch.cos(2 * math.pi * x)],
        dim=-1,
    )
    torch.testing.assert_close(out, expected)


def test_split_mlp_equals_the_concatenated_mlp() -> None:
    torch.manual_seed(0)
    mlp = DeltaMLP(point_dim=5, frame_dim=7, out_dim=3, width=16, depth=4)
    nn.init.normal_(mlp.output.weight)
    point, frame = torch.randn(11, 5), torch.randn(7)
    x = torch.cat([point, frame.expand(11, 7)], dim=-1)

    def joined(split) -> nn.Linear:
        lin = nn.Linear(12, 16)
        lin.weight.data = torch.cat([split.point.weight, split.frame.weight], dim=1)
        lin.bias.data = split.point.bias.clone()
        return lin

    first, skip = joined(mlp.input_layer), joined(mlp.skip)
    h = mlp.act(mlp.norms[0](first(x)))
    for i, layer in enumerate(mlp.hidden, start=1):
        z = layer(h) + (skip(x) if i == mlp.skip_at else 0)
        h = mlp.act(mlp.norms[i](z))
    torch.testing.assert_close(mlp(point, frame), mlp.output(h))


def test_relative_transform_is_invariant_to_moving_the_whole_scene() -> None:
    """r_rel, t_rel and the head-frame PBD offsets do not change when head and hand move rigidly together."""
    from scipy.spatial.transform import Rotation

    head, hand = procedural_head(), procedural_hand()
    params = scene_params([0.08])
    params["flame_global_orient"][:] = [0.1, -0.2, 0.05]
    params["mano_global_orient"][:] = [0.3, 0.1, -0.4]
    offsets = torch.full((1, head.num_vertices, 3), 0.002)
    a = sequence_conditioning(params, head, hand, offsets)
    # LBS poses a part as R_p (x - J) + J + t about its rest root joint J; moving it by (R, c) gives
    # (R R_p) (x - J) + J + t' with t' = R (J + t) + c - J.
    rest = {k: np.zeros_like(v) for k, v in params.items()}
    _, face, _, hand_out = pose_layers(rest, head, hand, torch.float64)
    roots = {"flame": face.joints[0, 0].numpy(), "mano": hand_out.joints[0, 0].numpy()}
    R, c = Rotation.from_rotvec([0.4, 0.7, -0.2]), np.array([0.3, -0.1, 0.2])
    moved = {k: v.copy() for k, v in params.items()}
    for part, J in roots.items():
        orient = Rotation.from_rotvec(params[f"{part}_global_orient"][0])
        moved[f"{part}_global_orient"] = (R * orient).as_rotvec()[None]
        moved[f"{part}_transl"] = (R.apply(J + params[f"{part}_transl"][0]) + c - J)[None]
    b = sequence_conditioning(moved, head, hand, torch.from_numpy(R.apply(offsets[0].numpy()))[None])
    for name in ("rel_rotation", "rel_translation", "face_offsets"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(
        b.head_origin[0], torch.from_numpy(R.apply(a.head_origin[0].numpy()) + c).float(), atol=1e-5, rtol=1e-5
    )


def test_geometry_sample_is_one_per_deforming_face_triangle_and_per_hand_triangle(scene: Scene) -> None:
    model = scene.model()
    cond = scene.cond.frame(NEAR)
    with torch.no_grad():
        means, scales, _ = model.gaussians.world(scene.meshes.vertices[NEAR], model.faces)
        points = model.geometry_points(cond, means, scales, model.gaussians.opacities(), torch.Generator())
    deforming = model.triangle_offsets(cond).norm(dim=-1) > model.cfg.deform_threshold_m
    hand_triangles = model.gaussians.binding[model.hand_index].unique().numel()
    face_triangles = model.gaussians.binding[model.face_index[deforming]].unique().numel()
    assert 0 < face_triangles
    assert points.shape == (face_triangles + hand_triangles, 3)


def test_one_per_triangle_sampling_follows_the_weights() -> None:
    """Triangle 0 holds weights 1 : 3, triangle 2 holds 2 : 2 : 4, triangle 1 is empty."""
    weight = torch.tensor([1.0, 3.0, 2.0, 2.0, 4.0])
    triangle = torch.tensor([0, 0, 2, 2, 2])
    gen = torch.Generator().manual_seed(1)
    draws = torch.stack([sample_one_per_triangle(weight, triangle, 3, gen) for _ in range(8000)])
    assert draws.shape == (8000, 2)  # one per non-empty triangle, in triangle order
    freq0 = torch.bincount(draws[:, 0], minlength=5).float() / 8000
    freq2 = torch.bincount(draws[:, 1], minlength=5).float() / 8000
    torch.testing.assert_close(freq0[:2], torch.tensor([0.25, 0.75]), atol=0.02, rtol=0)  # 4 sigma
    torch.testing.assert_close(freq2[2:], torch.tensor([0.25, 0.25, 0.5]), atol=0.025, rtol=0)
    assert sample_one_per_triangle(weight, triangle, 3, None).tolist() == [1, 4]  # evaluation: the largest
    assert sample_one_per_triangle(torch.ones(3), torch.zeros(3, dtype=torch.long), 1, None).tolist() == [0]
    assert sample_one_per_triangle(weight[:0], triangle[:0], 3, gen).numel() == 0


@pytest.mark.parametrize("case", ["hand_inside_face", "no_hand_visible", "empty_pointnet_input", "all_weights_zero"])
def test_extremes_stay_finite(case: str) -> None:
    if case == "hand_inside_face":
        scene = make_scene([-0.09], dent_m=0.02)  # the hand's root inside the head
    else:
        scene = make_scene([1.0])
    cfg = TINY
    if case == "empty_pointnet_input":
        cfg = DynamicModelConfig(**{**TINY.__dict__, "deform_threshold_m": 1.0})
    model = scene.model(cfg)
    if case == "empty_pointnet_input":  # no hand Gaussians and no deforming face triangle
        keep = model.gaussians.part == model.face_part
        model = _only(scene, model, keep, cfg)
    if case == "no_hand_visible":
        scene.views.world_to_cam[0, 2, 3] = -5.0  # everything behind the camera
    for head in (*model.hand_geo.heads.values(), *model.interaction.heads.values()):
        nn.init.normal_(head.output.weight, std=0.1)
    g = model(scene.cond.frame(0), scene.meshes.vertices[0], torch.Generator().manual_seed(0))
    out = rasterize(g, scene.views, 0)
    loss = out.rgb.sum() + g.local_scales.sum() + g.local_means.sum()
    loss.backward()
    for tensor in (g.means, g.scales, g.quats, g.opacities, g.colors, out.rgb):
        assert torch.isfinite(tensor).all()
    for name, p in model.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    if case == "all_weights_zero":
        assert g.interaction_evaluations == 0


def _only(scene: Scene, model, keep: torch.Tensor, cfg: DynamicModelConfig):
    """A model of the face Gaussians only (no hand Gaussian at all)."""
    from avatar.representations.bound.dynamic_model import DynamicAvatar
    from avatar.representations.bound.gaussians import BoundGaussians

    g = model.gaussians
    sub = BoundGaussians(
        *(getattr(g, n).detach()[keep] for n in ("local_means", "log_scales", "quats", "opacity_logits", "sh_dc")),
        binding=g.binding[keep],
        part=g.part[keep],
    )
    dims = {"hand_pose": scene.cond.hand_pose.shape[1], "expression": scene.cond.expression.shape[1]}
    return DynamicAvatar(
        sub, model.mu_cano[keep], model.faces, scene.meshes.part_names, scene.num_face_vertices, dims, cfg
    )


@pytest.mark.parametrize("colour_delta", ["add", "scale"])
def test_colour_delta_closed_forms(scene: Scene, colour_delta: str) -> None:
    """d_c enters as c_i + d_c (add) or c_i exp(d_c) (scale); both render the warm-up's colours at d_c = 0,
    and the interaction's d_c is weighted by w before either."""
    model = scene.model(dataclasses.replace(TINY, colour_delta=colour_delta))
    hand = model.hand_index
    with torch.no_grad():
        base = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
        rgb = torch.clamp_min(0.5 + SH_C0 * model.gaussians.sh_dc, 0.0)
        torch.testing.assert_close(base.colors, rgb if colour_delta == "scale" else base.colors)
        model.hand_app.heads["c"].output.bias.fill_(math.log(0.5))  # a uniform shadow on the hand
        shaded = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
    raw = 0.5 + SH_C0 * model.gaussians.sh_dc[hand]
    expected = raw.clamp_min(0) * 0.5 if colour_delta == "scale" else (raw + math.log(0.5)).clamp_min(0)
    torch.testing.assert_close(shaded.colors[hand], expected)
    face = model.face_index
    torch.testing.assert_close(shaded.colors[face], base.colors[face])


def test_a_huge_colour_log_scale_stays_finite(scene: Scene) -> None:
    model = scene.model(dataclasses.replace(TINY, colour_delta="scale"))
    with torch.no_grad():
        model.hand_app.heads["c"].output.bias.fill_(1e4)
        g = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR])
    assert torch.isfinite(g.colors).all()
