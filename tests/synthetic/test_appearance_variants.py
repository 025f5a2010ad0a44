"""The generator's appearance variants (dataset.appearance) and the held-out identity synth_c: what each variant
changes and what it leaves byte for byte, against the `full` capture of the same subject and motion."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from avatar.synthetic import SyntheticConfig, generate
from avatar.synthetic.appearance import BLANCH_STRENGTH, BLANCH_TINT, pressure_blanching
from avatar.synthetic.capture import SUBJECTS
from avatar.synthetic.identity import make_identity, motion_style
from avatar.synthetic.shading import srgb_encode
from avatar.templates.head import NUM_DESIGNED_SHAPE

SMALL = SyntheticConfig(subject="synth_a", sequence="train", image_size=48, num_frames=5, supersample=1, num_cameras=3)


@pytest.fixture(scope="module")
def captures() -> dict:
    return {a: generate(replace(SMALL, appearance=a)) for a in ("full", "plain", "pressed")}


def test_every_variant_has_the_same_geometry_masks_and_ground_truth(captures) -> None:
    full = captures["full"]
    for name in ("plain", "pressed"):
        other = captures[name]
        for cid in full.masks:
            np.testing.assert_array_equal(other.masks[cid], full.masks[cid])
            for part in full.keypoints[cid]:
                np.testing.assert_array_equal(other.keypoints[cid][part], full.keypoints[cid][part])
        for key in full.params:
            np.testing.assert_array_equal(other.params[key], full.params[key])
        np.testing.assert_array_equal(other.face_offsets, full.face_offsets)


def test_plain_takes_away_only_darkening(captures) -> None:
    """Creases, curl shadow and contact darkening multiply the light by at most 1: `full` is nowhere brighter
    than `plain` (beyond one 8-bit level of rounding), and darker on the hand in every frame."""
    full, plain = captures["full"], captures["plain"]
    for cid in full.frames:
        f, p = full.frames[cid].astype(int), plain.frames[cid].astype(int)
        assert (f <= p + 1).all()
        hand = full.masks[cid] == 2
        for t in range(f.shape[0]):
            if hand[t].sum() > 20:  # a relaxed hand has faint creases, a curled one deep ones
                assert (p[t][hand[t]] - f[t][hand[t]]).mean() > 0.1, (cid, t)
        background = full.masks[cid] == 0
        np.testing.assert_array_equal(f[background], p[background])


def test_pressed_blanches_the_dented_skin_and_leaves_every_other_frame_alone(captures) -> None:
    full, pressed = captures["full"], captures["pressed"]
    assert full.contact.any() and not full.contact.all()
    for cid in full.frames:
        for t in np.flatnonzero(~full.contact):
            np.testing.assert_array_equal(pressed.frames[cid][t], full.frames[cid][t])
    lighter = [
        (pressed.frames[cid][t].astype(int) - full.frames[cid][t].astype(int))[full.masks[cid][t] == 1].sum()
        for cid in full.frames
        for t in np.flatnonzero(full.contact)
    ]
    assert max(lighter) > 0 and min(lighter) >= 0


def test_pressure_blanching_against_its_closed_form() -> None:
    albedo = np.array([[0.5, 0.3, 0.2], [0.2, 0.1, 0.05], [0.4, 0.4, 0.4]])
    np.testing.assert_array_equal(pressure_blanching(albedo, np.zeros(3)), albedo)
    deep = pressure_blanching(albedo, np.full(3, 0.01))  # beyond full depth: the full blend
    pale = albedo.mean(1, keepdims=True) * BLANCH_TINT
    np.testing.assert_allclose(deep, (1 - BLANCH_STRENGTH) * albedo + BLANCH_STRENGTH * pale, rtol=1e-15)
    half = pressure_blanching(albedo, np.full(3, 0.002))
    np.testing.assert_allclose(half, (1 - BLANCH_STRENGTH / 2) * albedo + BLANCH_STRENGTH / 2 * pale, rtol=1e-12)


def test_an_unknown_appearance_is_refused_with_the_key() -> None:
    with pytest.raises(ValueError, match="dataset.appearance"):
        replace(SMALL, appearance="glossy")


def test_the_third_identity_differs_more_than_the_first_two_differ() -> None:
    """Head and hand shape, skin tone and motion: synth_c is further from each of synth_a and synth_b than those
    two are from each other."""
    a, b, c = (make_identity(s, NUM_DESIGNED_SHAPE) for s in SUBJECTS)
    # as seen: sRGB
    look = {"flame_shape": lambda x: x, "mano_shape": lambda x: x, "skin": lambda x: srgb_encode(x).astype(float)}
    for field, seen in look.items():
        ab = np.linalg.norm(seen(getattr(a, field)) - seen(getattr(b, field)))
        assert np.linalg.norm(seen(getattr(c, field)) - seen(getattr(a, field))) > ab, field
        assert np.linalg.norm(seen(getattr(c, field)) - seen(getattr(b, field))) > ab, field
    assert motion_style("synth_a") == motion_style("synth_b") != motion_style("synth_c")
    head = {
        s: generate(replace(SMALL, subject=s, image_size=16, num_cameras=2)).params["flame_global_orient"]
        for s in SUBJECTS
    }
    ab = np.abs(head["synth_a"] - head["synth_b"]).mean()
    assert np.abs(head["synth_c"] - head["synth_a"]).mean() > ab
    assert np.abs(head["synth_c"] - head["synth_b"]).mean() > ab
