"""Ground truth for cross-actor reenactment: one identity performing another subject's motion."""

from __future__ import annotations

import numpy as np
import pytest

from avatar.synthetic import SyntheticConfig, generate

SMALL = dict(sequence="test", image_size=16, num_frames=3, supersample=1, num_cameras=2)


def test_a_subject_performs_another_s_motion_with_its_own_identity():
    crossed = generate(SyntheticConfig(subject="synth_a", performer="synth_b", **SMALL))
    performer = generate(SyntheticConfig(subject="synth_b", **SMALL))
    own = generate(SyntheticConfig(subject="synth_a", **SMALL))
    for key in ("flame_expression", "flame_global_orient", "flame_neck_pose", "flame_jaw_pose", "flame_eye_pose"):
        np.testing.assert_array_equal(crossed.params[key], performer.params[key], err_msg=key)  # the motion
        assert not np.array_equal(crossed.params[key], own.params[key]), key
    for key in ("flame_shape", "mano_shape"):
        np.testing.assert_array_equal(crossed.params[key], own.params[key], err_msg=key)  # the identity
    # the hand is placed on this face as the script says, so it differs a little from the performer's
    assert 0 < np.abs(crossed.params["mano_transl"] - performer.params["mano_transl"]).max() < 0.05


def test_performing_one_s_own_motion_is_the_default():
    default = generate(SyntheticConfig(subject="synth_a", **SMALL))
    explicit = generate(SyntheticConfig(subject="synth_a", performer="synth_a", **SMALL))
    assert all(np.array_equal(default.params[k], explicit.params[k]) for k in default.params)
    assert all(np.array_equal(default.frames[c], explicit.frames[c]) for c in default.frames)
    with pytest.raises(ValueError, match="performer"):
        SyntheticConfig(subject="synth_a", performer="nobody", **SMALL)
