"""The generator's soft tissue over every contact frame of both subjects at ``quality=draft``: the face
conforms to the hand where the hand pushes it, never ends inside it, and leaves no gap under the contact
beyond the rim's lift-off (avatar/synthetic/soft_tissue.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.posing import posed_keypoints
from avatar.synthetic import SyntheticConfig, generate
from avatar.synthetic.geometry import signed_distance
from avatar.synthetic.soft_tissue import CLEARANCE_M
from avatar.templates import procedural_hand, procedural_head

#: quality=draft frame counts (conf/quality/draft.yaml)
DRAFT_FRAMES = {"train": 24, "test": 12}
#: Stated tolerances (mm) on the distance from the hand surface of the face vertices the hand overlaps
#: before deformation. Those the hand pushes sit at the clearance (0.3 mm); near the rim of the overlap
#: the membrane holds some below the hand's curving surface (measured: p95 1.4 / 1.8 mm, max 1.9 / 2.4 mm
#: on synth_a / synth_b; the previous model left p95 2.6 / 3.0 mm and max 4.4 mm, 36-47 % above 0.5 mm).
GAP_P95_MM, GAP_MAX_MM = 2.0, 2.6


@pytest.fixture(scope="module", params=["synth_a", "synth_b"])
def frames(request: pytest.FixtureRequest) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Per frame of both draft sequences: posed face (V, 3), hand (Vh, 3), offsets (V, 3), contact flag."""
    head, hand = procedural_head(), procedural_hand()
    out = []
    for sequence, count in DRAFT_FRAMES.items():
        cap = generate(
            SyntheticConfig(request.param, sequence, image_size=16, num_frames=count, supersample=1, num_cameras=2)
        )
        posed = posed_keypoints(cap.params, head, hand)
        out += list(zip(posed["face_vertices"], posed["hand_vertices"], cap.face_offsets, cap.contact))
    return out


def test_pressed_vertices_end_on_the_hand_and_none_inside(frames: list) -> None:
    hand_faces = torch.as_tensor(np.array(procedural_hand().faces))
    gaps, contact_frames = [], 0
    for face, hand, offsets, contact in frames:
        if not contact:
            continue
        contact_frames += 1
        face, hand = torch.as_tensor(face), torch.as_tensor(hand)
        before, _, _ = signed_distance(face, hand, hand_faces)
        after, _, _ = signed_distance(face + torch.as_tensor(offsets), hand, hand_faces)
        assert after.min() >= 0.0, "a face vertex ends inside the hand"
        pressed = before < 0
        assert pressed.any()
        deepest = int(before.argmin())  # the hand pushes it: it sits at the clearance
        assert abs(float(after[deepest]) - CLEARANCE_M) < 1e-6
        gaps.append(after[pressed].numpy() * 1e3)
    gap = np.concatenate(gaps)
    assert contact_frames >= 10
    assert np.percentile(gap, 95) < GAP_P95_MM and gap.max() < GAP_MAX_MM


def test_frames_without_contact_are_untouched(frames: list) -> None:
    """No contact: the offsets are exactly zero (so those frames render byte for byte as before the change)."""
    quiet = [offsets for _, _, offsets, contact in frames if not contact]
    assert quiet and all(not offsets.any() for offsets in quiet)
