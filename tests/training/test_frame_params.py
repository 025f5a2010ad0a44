"""Per-frame parameters refined with the avatar (avatar.training.frame_params): the row-wise Adam against torch's
Adam, the posed meshes and conditioning against the sequence posing, the gradient against a closed form, and the
params.parquet round trip."""

from __future__ import annotations

import functools
from dataclasses import fields

import numpy as np
import pytest
import torch

from avatar.artifacts import read_params, write_params
from avatar.dynamic.conditioning import sequence_conditioning
from avatar.geometry.views import ViewSet
from avatar.posing import posed_meshes
from avatar.representations.bound import warmup
from avatar.representations.bound.gaussians import BoundGaussians
from avatar.representations.bound.warmup import WarmupTrainConfig, train_warmup
from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate
from avatar.templates import procedural_hand, procedural_head
from avatar.training.frame_params import (
    REFINED_COLUMNS,
    FrameAdam,
    FrameParams,
    ParamLearningRates,
    parameter_movement,
)

HEAD, HAND = procedural_head(), procedural_hand()


@functools.cache
def _capture() -> SyntheticCapture:
    return generate(SyntheticConfig(subject="synth_a", sequence="train", image_size=32, num_frames=4, supersample=1))


def _params() -> dict[str, np.ndarray]:
    """Four frames of synth_a's train motion (a fresh float32 copy)."""
    return {k: np.asarray(v, dtype=np.float32).copy() for k, v in _capture().params.items()}


def _views(cameras: int = 2) -> ViewSet:
    """The capture's first ``cameras`` full 32 px images of every frame."""
    capture = _capture()
    cams = capture.cameras[:cameras]
    images = np.stack([capture.frames[c.camera_id] for c in cams], 1)
    labels = np.stack([capture.masks[c.camera_id] for c in cams], 1)
    return ViewSet(
        torch.from_numpy(images),
        torch.from_numpy(labels),
        torch.tensor(np.stack([c.K for c in cams]), dtype=torch.float32),
        torch.tensor(np.stack([c.world_to_cam for c in cams]), dtype=torch.float32),
        [c.camera_id for c in cams],
        torch.tensor([0.5, 0.5, 0.5]),
    )


def test_frame_adam_is_torch_adam_on_each_row_alone():
    gen = torch.Generator().manual_seed(0)
    rows = torch.randn(3, 5, generator=gen)
    param = torch.nn.Parameter(rows.clone())
    frame_adam = FrameAdam([(param, 0.01)], num_frames=3)
    alone = [torch.nn.Parameter(rows[t].clone()) for t in range(3)]
    references = [torch.optim.Adam([p], lr=0.01, eps=1e-15) for p in alone]
    for frame in [0, 2, 2, 0, 2, 1, 2]:  # rows stepped a different number of times
        grad = torch.randn(5, generator=gen)
        param.grad = torch.zeros_like(param)
        param.grad[frame] = grad
        frame_adam.step(frame)
        assert param.grad is None
        alone[frame].grad = grad.clone()
        references[frame].step()
        for t in range(3):  # every row as if it had its own optimiser: unstepped rows do not move
            torch.testing.assert_close(param.detach()[t], alone[t].detach(), rtol=0, atol=1e-7)
    assert frame_adam.steps.tolist() == [2, 1, 4]


def test_a_scaled_step_is_adam_at_the_scaled_rate():
    gen = torch.Generator().manual_seed(1)
    rows = torch.randn(2, 4, generator=gen)
    param = torch.nn.Parameter(rows.clone())
    frame_adam = FrameAdam([(param, 0.01)], num_frames=2)
    reference = torch.nn.Parameter(rows[1].clone())
    adam = torch.optim.Adam([reference], lr=0.01, eps=1e-15)
    for scale in (1.0, 0.5, 0.25):  # a schedule: each update at its own rate, the moments as Adam keeps them
        grad = torch.randn(4, generator=gen)
        param.grad = torch.zeros_like(param)
        param.grad[1] = grad
        frame_adam.step(1, lr_scale=scale)
        reference.grad = grad.clone()
        adam.param_groups[0]["lr"] = 0.01 * scale
        adam.step()
        torch.testing.assert_close(param.detach()[1], reference.detach(), rtol=0, atol=1e-7)
    torch.testing.assert_close(param.detach()[0], rows[0], rtol=0, atol=0)


def test_posing_and_conditioning_match_the_sequence_posing():
    params = _params()
    offsets = 1e-3 * torch.randn(4, HEAD.num_vertices, 3, generator=torch.Generator().manual_seed(1))
    frames = FrameParams(params, HEAD, HAND, offsets, ParamLearningRates())
    meshes = posed_meshes(params, HEAD, HAND)
    meshes.vertices[:, : HEAD.num_vertices] += offsets
    cond = sequence_conditioning(params, HEAD, HAND, offsets)
    for t in range(4):
        torch.testing.assert_close(frames.vertices(t).detach(), meshes.vertices[t], rtol=0, atol=1e-6)
        one = frames.conditioning(t)
        for f in fields(one):
            torch.testing.assert_close(getattr(one, f.name), getattr(cond.frame(t), f.name), rtol=0, atol=1e-5)


def test_translation_gradient_is_the_vertex_count_and_only_the_rendered_row_moves():
    """d(sum of the face's x) / d(flame_transl x) = V_face exactly; the hand's translation gets the hand's count."""
    params = _params()
    frames = FrameParams(params, HEAD, HAND, None, ParamLearningRates())
    vertices = frames.vertices(2)
    vertices[:, 0].sum().backward()
    grad_face, grad_hand = frames.rows["flame_transl"].grad, frames.rows["mano_transl"].grad
    np.testing.assert_allclose(grad_face[2].numpy(), [HEAD.num_vertices, 0, 0], atol=1e-3)
    np.testing.assert_allclose(grad_hand[2].numpy(), [HAND.num_vertices, 0, 0], atol=1e-3)
    assert not grad_face[[0, 1, 3]].any()
    before = {k: v.copy() for k, v in frames.arrays().items()}
    frames.step(2, np.arange(4))
    after = frames.arrays()
    for k in before:
        np.testing.assert_array_equal(np.delete(after[k], 2, 0), np.delete(before[k], 2, 0))
    assert not np.array_equal(after["flame_transl"][2], before["flame_transl"][2])
    np.testing.assert_array_equal(after["flame_shape"], before["flame_shape"])  # the identity is never refined
    assert "flame_shape" not in frames.rows and "mano_shape" not in frames.rows
    assert {c for cols in REFINED_COLUMNS.values() for c in cols} == set(frames.rows)


def test_refined_parameters_round_trip_through_params_parquet(tmp_path):
    params = _params()
    frames = FrameParams(params, HEAD, HAND, None, ParamLearningRates(translation=1e-3, rotation=1e-2))
    for t in (0, 3):
        (frames.vertices(t) ** 2).sum().backward()
        frames.step(t, np.arange(4))
    written = frames.arrays()
    write_params(tmp_path / "params.parquet", written)
    back = read_params(tmp_path / "params.parquet")
    for k, v in written.items():
        np.testing.assert_array_equal(np.asarray(back[k], dtype=np.float32), v)
    again = FrameParams(back, HEAD, HAND, None, ParamLearningRates())
    for t in range(4):
        torch.testing.assert_close(again.vertices(t), frames.vertices(t), rtol=0, atol=0)
    moved = parameter_movement(params, back, HEAD, HAND)
    assert moved["moved_mm"]["face"][[1, 2]].max() == 0 and moved["moved_mm"]["face"][[0, 3]].min() > 0
    np.testing.assert_allclose(moved["rotated_deg"]["hand"][[1, 2]], 0, atol=1e-6)


def test_centred_corrections_have_zero_mean_over_the_refined_frames_and_leave_the_others():
    params = _params()
    frames = FrameParams(params, HEAD, HAND, None, ParamLearningRates(translation=1e-3, rotation=1e-2), centred=True)
    refined = np.array([0, 1, 3])  # frame 2 withheld (a validation frame): never rendered, never moved
    for t in (0, 3, 3, 1):
        (frames.vertices(t)[:, 1] * (t + 1)).sum().backward()
        frames.step(t, refined)
    after = frames.arrays()
    for k in frames.rows:
        correction = after[k][refined] - params[k][refined]
        np.testing.assert_allclose(correction.mean(0), 0, atol=1e-6)
        np.testing.assert_array_equal(after[k][2], params[k][2])
    assert np.abs(after["flame_transl"][refined] - params["flame_transl"][refined]).max() > 1e-4  # it did move


def test_learning_rates_refuse_negative_and_nan():
    assert ParamLearningRates().problems() == []
    problems = ParamLearningRates(rotation=-1.0, expression=float("nan")).problems()
    assert len(problems) == 2 and problems[0].startswith("rotation=-1")


def test_a_killed_warmup_resumes_the_refinement_to_the_same_result(tmp_path, monkeypatch):
    """The refined parameters and their per-frame Adam state are in the checkpoint: killed after the checkpoint
    of step 10 and resumed, the run ends with the parameters of the run that was never killed (to float32 rounding,
    as the warm-up's own resume test)."""
    params, views = _params(), _views(cameras=1)
    meshes = posed_meshes(params, HEAD, HAND)
    cfg = WarmupTrainConfig(
        steps=20,
        densify_from=0.5,
        densify_until=0.9,
        densify_interval=0.5,
        opacity_reset_interval=1.0,
        log_every=4,
        checkpoint_every=10,
    )
    lrs = ParamLearningRates(translation=1e-4, rotation=1e-3, pose=1e-3, expression=1e-2)

    def run(checkpoint_dir=None) -> FrameParams:
        model = BoundGaussians.on_triangles(meshes.vertices[0], meshes.faces, meshes.face_part, 1, init_opacity=0.3)
        frames = FrameParams(params, HEAD, HAND, None, lrs, centred=True)
        train_warmup(model, views, meshes, cfg, checkpoint_dir=checkpoint_dir, params=frames)
        return frames

    reference = run().arrays()
    real_render, calls = warmup.render_frame, {"n": 0}

    def dying_render(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 13:
            raise KeyboardInterrupt("killed")
        return real_render(*args, **kwargs)

    monkeypatch.setattr(warmup, "render_frame", dying_render)
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path)
    monkeypatch.setattr(warmup, "render_frame", real_render)
    resumed = run(tmp_path).arrays()
    assert any(not np.array_equal(reference[k], params[k]) for k in reference)  # it refined
    for k in reference:
        np.testing.assert_allclose(resumed[k], reference[k], rtol=1e-5, atol=1e-6)
