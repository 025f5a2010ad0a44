"""Scene analysis against brute force and on hand-made scenes."""

from __future__ import annotations

import numpy as np
import pytest

from avatar.scene import SceneFacts, decide, deforming_triangles, hand_face_distances, scene_facts

AUTO = {"model_hand": "auto", "model_pbd": "auto", "model_interaction": "auto"}


def test_distances_match_brute_force():
    rng = np.random.default_rng(0)
    face, hand = rng.normal(size=(3, 50, 3)), rng.normal(size=(3, 20, 3)) + 0.5
    brute = np.linalg.norm(face[:, :, None] - hand[:, None], axis=-1).min(axis=2)
    np.testing.assert_allclose(hand_face_distances(face, hand), brute, atol=1e-12)


def _facts(hand_views: list[int], nearest: list[float], V: int = 4) -> SceneFacts:
    """Facts of frames whose first face vertex is ``nearest`` from the hand, the others 1 m away."""
    distances = np.ones((len(nearest), V))
    distances[:, 0] = nearest
    return scene_facts(np.array(hand_views), distances, min_views=2, d_max=0.05)


def test_contact_needs_the_hand_in_view_and_within_d_max():
    facts = _facts([3, 3, 1, 0], [0.01, 0.2, 0.01, 0.0])
    np.testing.assert_array_equal(facts.hand_present, [True, True, False, False])
    np.testing.assert_array_equal(facts.contact, [True, False, False, False])
    assert np.isnan(facts.distance_m[2:]).all() and facts.distance_m[0] == pytest.approx(0.01)
    np.testing.assert_array_equal(facts.near_vertices.sum(axis=1), [1, 0, 0, 0])


def test_decisions_for_the_three_scenes_and_their_reasons():
    interaction = decide(_facts([3, 3, 3], [0.2, 0.01, 0.2]), 0.05, AUTO)
    assert (interaction.model_hand, interaction.model_pbd, interaction.model_interaction) == (True, True, True)
    no_contact = decide(_facts([3, 3, 3], [0.2, 0.07, 0.2]), 0.05, AUTO)
    assert (no_contact.model_hand, no_contact.model_pbd, no_contact.model_interaction) == (True, False, False)
    assert "never comes within d_max" in no_contact.why["model_pbd"] and "70 mm" in no_contact.why["model_pbd"]
    face_only = decide(_facts([0, 1, 0], [0.0, 0.0, 0.0]), 0.05, AUTO)
    assert (face_only.model_hand, face_only.model_pbd, face_only.model_interaction) == (False, False, False)
    assert "face-only" in face_only.why["model_hand"] and len(face_only.reasons) == 3


def test_the_config_overrides_a_decision_and_says_so():
    forced = decide(_facts([3, 3], [0.2, 0.2]), 0.05, {**AUTO, "model_interaction": "true"})
    assert forced.model_interaction and not forced.model_pbd
    assert "set in the config (stage.scene.model_interaction)" in forced.why["model_interaction"]
    with pytest.raises(ValueError, match="auto, true or false"):
        decide(_facts([3], [0.2]), 0.05, {**AUTO, "model_pbd": "maybe"})


def test_deforming_triangles_are_those_touching_a_near_vertex():
    near = np.array([[True, False, False, False, False], [False, False, False, False, False]])
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [0, 3, 4]])
    np.testing.assert_array_equal(deforming_triangles(near, faces), [True, False, False, True])


def test_a_hand_forced_on_that_is_never_seen_has_no_contact_to_model():
    forced = decide(_facts([0, 0], [0.0, 0.0]), 0.05, {**AUTO, "model_hand": "true"})
    assert forced.model_hand and not forced.model_pbd and "never in view" in forced.why["model_pbd"]
