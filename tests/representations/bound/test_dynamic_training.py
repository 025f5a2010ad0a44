"""Stage-two training: every part learns, a killed run resumes to the same bits, contact oversampling, L_patch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.losses import patch_perceptual_loss
from avatar.metrics.lpips import LPIPS
from avatar.representations.bound.stage_two import (
    DynamicTrainConfig,
    contact_draw_probability,
    patch_boxes,
    rasterize,
    sample_frame,
    train_dynamic,
)
from avatar.training.selection import SelectionConfig
from avatar.training.validation import ValidationConfig, Validator
from tests.representations.bound.conftest import NEAR, Scene

CONTACT = np.array([True, False])


class _Kill(Exception):
    pass


def _cfg(steps: int, **kw) -> DynamicTrainConfig:
    return DynamicTrainConfig(steps=steps, backend="auto", patch_min_size=16, log_every=1, **kw)


@pytest.fixture(scope="module")
def lpips() -> LPIPS:
    return LPIPS("vgg")


def test_every_network_the_point_features_and_the_gaussians_receive_gradients(scene: Scene, lpips: LPIPS) -> None:
    model = scene.model()
    # two steps move the zero output layers off zero; then every layer upstream of them gets a gradient
    train_dynamic(
        model,
        scene.views,
        scene.meshes,
        scene.cond,
        CONTACT,
        _cfg(2, contact_fraction=1.0, max_contact_emphasis=1e9),
        lpips=lpips,
    )
    g = model(scene.cond.frame(NEAR), scene.meshes.vertices[NEAR], torch.Generator().manual_seed(0))
    out = rasterize(g, scene.views, 0)
    (out.rgb - scene.views.image(NEAR, 0)).square().mean().backward()
    missing = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert missing == []
    assert {"point_features", "gaussians.local_means", "gaussians.sh_dc"} <= {n for n, _ in model.named_parameters()}
    assert any(n.startswith("pointnet.") for n, _ in model.named_parameters())


def test_a_killed_run_resumes_to_the_same_result(scene: Scene, tmp_path, lpips: LPIPS) -> None:
    cfg = _cfg(4, checkpoint_every=2)
    straight = scene.model()
    log = train_dynamic(straight, scene.views, scene.meshes, scene.cond, CONTACT, cfg, lpips=lpips).log

    def killed_after_two(steps):
        for step in steps:
            if step == 3:
                raise _Kill
            yield step

    resumed = scene.model()
    with pytest.raises(_Kill):
        train_dynamic(
            resumed, scene.views, scene.meshes, scene.cond, CONTACT, cfg, tmp_path, killed_after_two, lpips=lpips
        )
    resumed = scene.model()  # a fresh process: the model starts from the warm-up again
    result = train_dynamic(resumed, scene.views, scene.meshes, scene.cond, CONTACT, cfg, tmp_path, lpips=lpips)
    for (name, a), (_, b) in zip(straight.state_dict().items(), resumed.state_dict().items(), strict=True):
        assert torch.equal(a, b), name
    assert [r.loss for r in result.log] == [r.loss for r in log]


def test_contact_frames_are_oversampled() -> None:
    gen = torch.Generator().manual_seed(0)
    contact = np.zeros(10, bool)
    contact[[2, 7]] = True
    draws = np.array([sample_frame(gen, np.arange(10), contact, 0.5) for _ in range(4000)])
    share = np.isin(draws, [2, 7]).mean()
    assert abs(share - (0.5 + 0.5 * 0.2)) < 0.03
    assert set(np.unique(draws)) == set(range(10))
    none = np.array([sample_frame(gen, np.arange(10), np.zeros(10, bool), 0.5) for _ in range(200)])
    assert set(np.unique(none)) == set(range(10))  # no contact frame: uniform over all


def test_patch_boxes_and_loss(lpips: LPIPS) -> None:
    labels = np.zeros((40, 40), np.uint8)
    labels[5:30, 5:30] = 1  # face
    labels[20:26, 24:36] = 2  # hand, overlapping the face box
    boxes = patch_boxes(labels)
    np.testing.assert_array_equal(boxes[0], [24, 20, 36, 26])
    np.testing.assert_array_equal(boxes[1], [24, 20, 30, 26])
    gen = torch.Generator().manual_seed(0)
    pred, gt = torch.rand(40, 40, 3, generator=gen), torch.rand(40, 40, 3, generator=gen)
    loss = patch_perceptual_loss(pred, gt, boxes, lpips, min_size=16)
    # each box grows about its centre to 16 px a side, inside the image
    expected = lpips(pred[15:31, 22:38].permute(2, 0, 1), gt[15:31, 22:38].permute(2, 0, 1), unit_range=True) + lpips(
        pred[15:31, 19:35].permute(2, 0, 1), gt[15:31, 19:35].permute(2, 0, 1), unit_range=True
    )
    torch.testing.assert_close(loss, expected)
    assert patch_perceptual_loss(pred, gt, [], lpips) == 0
    assert patch_boxes(np.ones((8, 8), np.uint8)) == []  # no hand: no patch


def test_the_selection_keeps_the_best_validated_step_and_resumes_to_the_same_choice(
    scene: Scene, tmp_path, lpips: LPIPS
) -> None:
    """With selection on, the model left is the best validation point's (step 0, the warm-up, included), less
    the modules that did not pay for themselves; its validation PSNR re-measured is the one recorded, and a
    killed run resumes to the same choice, bit for bit."""
    cfg = _cfg(4, checkpoint_every=1, selection=SelectionConfig(enabled=True, margin_db=0.05))
    validation = ValidationConfig(every=2, frames=1)
    validator = Validator(validation, scene.views)
    model = scene.model()
    result = train_dynamic(model, scene.views, scene.meshes, scene.cond, CONTACT, cfg, lpips=lpips, validator=validator)
    chosen = result.selection
    curve = [(p.step, p.psnr) for p in validator.curve]
    assert [s for s, _ in curve] == [0, 2, 4]
    best = max(curve, key=lambda point: (point[1], -point[0]))
    assert (chosen.selected_step, chosen.selected_psnr) == best
    assert (chosen.final_step, chosen.final_psnr) == curve[-1]
    assert set(chosen.kept) == {"hand_mlp", "interaction"} and set(chosen.psnr_without) == {"hand_mlp", "interaction"}

    def render(frame: int) -> torch.Tensor:
        g = model(scene.cond.frame(frame), scene.meshes.vertices[frame])
        return torch.stack([rasterize(g, scene.views, c).rgb for c in range(scene.views.num_cameras)])

    assert validator.measure(render) == pytest.approx(chosen.psnr, abs=1e-9)

    def killed_after_three(steps):
        for step in steps:
            if step == 4:
                raise _Kill
            yield step

    with pytest.raises(_Kill):
        train_dynamic(
            scene.model(),
            scene.views,
            scene.meshes,
            scene.cond,
            CONTACT,
            cfg,
            tmp_path,
            killed_after_three,
            lpips=lpips,
            validator=Validator(validation, scene.views),
        )
    resumed = scene.model()
    again = train_dynamic(
        resumed,
        scene.views,
        scene.meshes,
        scene.cond,
        CONTACT,
        cfg,
        tmp_path,
        lpips=lpips,
        validator=Validator(validation, scene.views),
    ).selection
    assert again == chosen
    for (name, a), (_, b) in zip(model.state_dict().items(), resumed.state_dict().items(), strict=True):
        assert torch.equal(a, b), name


def test_the_selection_needs_validation_frames(scene: Scene, lpips: LPIPS) -> None:
    cfg = _cfg(1, selection=SelectionConfig(enabled=True))
    with pytest.raises(ValueError, match="stage.dynamic.validation.every"):
        train_dynamic(scene.model(), scene.views, scene.meshes, scene.cond, CONTACT, cfg, lpips=lpips)


def _emphasis_cap(k: int, frames: int, cap: float) -> float:
    """The closed form: p with 1 + p K / ((1 - p) k) = cap."""
    return (cap - 1) * k / (frames + (cap - 1) * k)


@pytest.mark.parametrize(
    ("contact_ids", "frames", "expected"),
    [
        ([1], 4, 2 / 6),  # K = 4, one contact frame: capped to emphasis 3
        ([0, 1], 4, 0.5),  # K = 4, half the frames touch: 1 + 0.5 * 4 / (0.5 * 2) = 3, the cap exactly
        ([0], 8, 2 / 10),  # K = 8 (issue 53's short captures), one contact frame: 30 % of the steps, not 56 %
        ([0, 1, 2], 8, 6 / 14),  # three of eight
        ([0, 1, 2, 3], 8, 0.5),  # half of eight: the paper's 0.5, untouched
        ([0, 1, 2], 24, 6 / 30),  # K = 24, a few contact frames among many
        (list(range(12)), 24, 0.5),  # the synthetic draft captures: half the frames touch, the cap does not bite
        (list(range(15)), 24, 0.5),
        ([], 24, 0.5),
        (list(range(24)), 24, 0.5),  # nothing to oversample: contact_fraction as given (no effect)
    ],
)
def test_contact_draw_probability_caps_each_contact_frames_emphasis(contact_ids, frames, expected) -> None:
    contact = np.isin(np.arange(frames), contact_ids)
    p = contact_draw_probability(np.arange(frames), contact, 0.5, 3.0)
    assert p == pytest.approx(expected)
    k = len(contact_ids)
    if 0 < k < frames:
        assert p == pytest.approx(min(0.5, _emphasis_cap(k, frames, 3.0)))
        contact_share, other_share = p / k + (1 - p) / frames, (1 - p) / frames
        assert contact_share / other_share <= 3.0 + 1e-9  # no contact frame drawn more than 3 times as often
        gen = torch.Generator().manual_seed(0)  # the closed form against the shares sample_frame realises
        draws = np.array([sample_frame(gen, np.arange(frames), contact, p) for _ in range(20000)])
        assert abs(np.mean(draws == contact_ids[0]) - contact_share) < 0.01
        other = int(np.setdiff1d(np.arange(frames), contact_ids)[0])
        assert abs(np.mean(draws == other) - other_share) < 0.01
    assert contact_draw_probability(np.arange(frames), contact, 0.5, 1.0) == (0.0 if 0 < k < frames else 0.5)
    assert contact_draw_probability(np.arange(frames), contact, 0.5, 1e12) == pytest.approx(0.5)  # uncapped: paper


def test_a_fully_capped_oversampling_trains_exactly_as_uniform_drawing(scene: Scene, lpips: LPIPS) -> None:
    """Emphasis cap 1 leaves nothing to oversample, and the run is the contact_fraction=0 run."""
    runs = []
    for fraction in (0.0, 0.5):
        model = scene.model()
        cfg = _cfg(3, contact_fraction=fraction, max_contact_emphasis=1.0)
        log = train_dynamic(model, scene.views, scene.meshes, scene.cond, CONTACT, cfg, lpips=lpips).log
        runs.append(([r.loss for r in log], model.state_dict()))
    assert runs[0][0] == runs[1][0]
    for (name, a), (_, b) in zip(runs[0][1].items(), runs[1][1].items(), strict=True):
        assert torch.equal(a, b), name


def test_the_cap_counts_only_the_training_frames() -> None:
    """Contact frames withheld for validation are not drawn, so they do not count."""
    contact = np.isin(np.arange(24), range(12))
    train = np.arange(8, 24)  # 4 contact frames of 16 left to training
    assert contact_draw_probability(train, contact, 0.5, 3.0) == pytest.approx(_emphasis_cap(4, 16, 3.0))
