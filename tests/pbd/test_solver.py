"""The per-frame solve: no contact, the same press on cheek and forehead, extremes, sequences."""

from __future__ import annotations

import pytest
import torch

from avatar.pbd import PBDConfig, solve_frame, solve_sequence
from avatar.pbd.collision import query_hand
from avatar.templates.layers import MANOLayer
from avatar.templates.procedural import procedural_hand
from tests.pbd.conftest import Head, press, sphere

CFG = PBDConfig()


def _solve(
    head: Head,
    hand: torch.Tensor,
    hand_faces: torch.Tensor,
    stiffness: torch.Tensor | None = None,
    rest: torch.Tensor | None = None,
):  # FrameResult
    return solve_frame(
        head.vertices if rest is None else rest,
        hand,
        hand_faces,
        head.topology,
        head.stiffness if stiffness is None else stiffness,
        CFG,
    )


def _check_bounded(
    head: Head,
    result,
    hand: torch.Tensor,
    hand_faces: torch.Tensor,
    bound_m: float = 0.06,
) -> None:
    assert torch.isfinite(result.offsets).all()
    assert result.max_offset_m < bound_m
    assert result.penetration_max_m < 3e-4


def test_far_hand_is_not_simulated_and_offsets_are_exactly_zero(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    far, faces = sphere(head.vertices[cheek] + 0.05 * head.normals[cheek], 0.01)
    r = _solve(head, far, faces)
    assert not r.near and not r.simulated
    assert torch.count_nonzero(r.offsets) == 0 and not r.face_contact.any() and not r.hand_contact.any()
    close, faces = sphere(head.vertices[cheek] + 0.0125 * head.normals[cheek], 0.01)  # 2.5 mm gap: near, no contact
    r = _solve(head, close, faces)
    assert r.near and not r.simulated and torch.count_nonzero(r.offsets) == 0


def test_press_leaves_no_penetration_and_flags_both_sides(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.005)
    r = _solve(head, hand, faces)
    assert r.simulated and r.face_contact[cheek] and r.hand_contact.any()
    moved = head.vertices + r.offsets
    q = query_hand(moved, hand, faces, CFG.max_depth_m)
    assert q.depth.max() < 3e-4 and r.penetration_max_m < 3e-4
    assert (r.offsets[cheek] @ head.normals[cheek]) < -0.004  # pushed into the face


def test_the_same_press_moves_the_cheek_more_than_the_forehead(head: Head) -> None:
    def dent(region: str) -> float:
        centre = head.centre_of(region)
        hand, faces = press(head, centre, 0.004)
        r = _solve(head, hand, faces)
        around = (head.vertices - head.vertices[centre]).norm(dim=1) < 0.02
        return float(r.offsets[around].norm(dim=1).sum())

    assert dent("cheek_left") > 1.3 * dent("forehead")


def test_hand_three_centimetres_deep_in_the_cheek(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    hand, faces = sphere(head.vertices[cheek] - 0.01 * head.normals[cheek], 0.02)  # reaches 3 cm under the skin
    r = _solve(head, hand, faces)
    assert r.simulated
    _check_bounded(head, r, hand, faces)


def test_fully_bent_fingers_pressed_into_the_face(head: Head) -> None:
    model = procedural_hand()
    pose = torch.zeros(1, 45, dtype=torch.float64)
    pose[0, 0::3] = 1.6  # every finger joint fully flexed
    out = MANOLayer(model)(torch.zeros(1, model.num_shapes_total, dtype=torch.float64), pose)
    hand, faces = out.vertices[0], torch.tensor(model.faces)
    cheek = head.centre_of("cheek_left")
    knuckles = hand[hand[:, 2].argmax()]  # the hand's most +z point, pushed 8 mm into the cheek
    hand = hand - knuckles + head.vertices[cheek] - 0.008 * head.normals[cheek]
    r = _solve(head, hand, faces)
    assert r.simulated
    _check_bounded(head, r, hand, faces)


def test_degenerate_triangle_and_zero_stiffness_vertex(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.005)
    rest = head.vertices.clone()
    a, b, _ = head.faces[(head.faces == cheek).any(dim=1).nonzero()[0, 0]]
    rest[b] = rest[a]  # collapse an edge of a triangle under the press: zero area
    r = _solve(head, hand, faces, rest=rest)
    _check_bounded(head, r, hand, faces)
    stiffness = head.stiffness.clone()
    stiffness[cheek] = 0.0
    r = _solve(head, hand, faces, stiffness=stiffness)
    _check_bounded(head, r, hand, faces)


def test_sequences_single_frame_and_nan(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.004)
    one = solve_sequence(head.vertices[None], hand[None], head.faces, faces, head.stiffness, CFG)
    assert len(one) == 1 and one[0].simulated
    face = head.vertices[None].repeat(3, 1, 1)
    hands = hand[None].repeat(3, 1, 1)
    warm = solve_sequence(face, hands, head.faces, faces, head.stiffness, PBDConfig(warm_start=True))
    assert all(r.penetration_max_m < 3e-4 for r in warm)
    assert float((warm[2].offsets - one[0].offsets).norm(dim=1).max()) < 1e-3  # the same press, warm or cold
    hands[2, 5, 1] = float("nan")
    with pytest.raises(ValueError, match="frame 2: the posed hand"):
        solve_sequence(face, hands, head.faces, faces, head.stiffness, CFG)


@pytest.mark.parametrize(
    "bad",
    [
        {"method": "newton"},
        {"relaxation": 6.0},
        {"detect_every": 0},
        {"chebyshev_rho": 0.5, "method": "gauss_seidel"},
        {"margin_m": 0.0},
        {"attach_stiffness": -1.0},
    ],
)
def test_bad_settings_are_refused_by_name(bad: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        PBDConfig(**bad)


def test_chebyshev_reaches_the_plain_jacobi_solution_sooner(head: Head) -> None:
    """In the soft regime (weak attachments, no shear), where plain Jacobi sweeps converge slowly."""
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.005)
    soft = {"method": "jacobi", "shear_stiffness": 0.0, "attach_stiffness": 60.0}
    plain = solve_frame(
        head.vertices, hand, faces, head.topology, head.stiffness, PBDConfig(**soft, chebyshev_rho=0.0, iterations=3000)
    )
    fast = solve_frame(head.vertices, hand, faces, head.topology, head.stiffness, PBDConfig(**soft))
    short = solve_frame(
        head.vertices,
        hand,
        faces,
        head.topology,
        head.stiffness,
        PBDConfig(**soft, chebyshev_rho=0.0, iterations=CFG.iterations),
    )
    gap = lambda r: float((r.offsets - plain.offsets).norm(dim=1).max())  # noqa: E731
    assert gap(fast) < 0.5 * gap(short)


DIRECT = PBDConfig(method="direct")


def test_direct_solve_lands_on_the_converged_sweeps(head: Head) -> None:
    """method=direct minimises what the XPBD sweeps converge to: it agrees with many Gauss-Seidel sweeps
    (closer than 300 Jacobi sweeps do), leaves no penetration and dents cheek over forehead."""
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.005)
    direct = solve_frame(head.vertices, hand, faces, head.topology, head.stiffness, DIRECT)
    converged = solve_frame(
        head.vertices,
        hand,
        faces,
        head.topology,
        head.stiffness,
        PBDConfig(method="gauss_seidel", chebyshev_rho=0.0, iterations=3000, detect_every=50),
    )
    default = solve_frame(head.vertices, hand, faces, head.topology, head.stiffness, PBDConfig(method="jacobi"))
    gap = lambda r: (r.offsets - converged.offsets).norm(dim=1)  # noqa: E731
    assert direct.simulated and direct.penetration_max_m < 3e-4
    assert float(gap(direct).mean()) < 1e-5 and float(gap(direct).max()) < 1e-3
    assert float(gap(direct).mean()) < float(gap(default).mean())

    def dent(region: str) -> float:
        centre = head.centre_of(region)
        hand, faces = press(head, centre, 0.004)
        r = solve_frame(head.vertices, hand, faces, head.topology, head.stiffness, DIRECT)
        return float(r.offsets[(head.vertices - head.vertices[centre]).norm(dim=1) < 0.02].norm(dim=1).sum())

    assert dent("cheek_left") > 1.3 * dent("forehead")


def test_direct_volume_term_stays_bounded_and_is_refused_elsewhere(head: Head) -> None:
    cheek = head.centre_of("cheek_left")
    hand, faces = press(head, cheek, 0.03, radius=0.02)  # 3 cm deep
    stiffness = head.stiffness.clone()
    stiffness[cheek] = 0.0
    r = solve_frame(
        head.vertices, hand, faces, head.topology, stiffness, PBDConfig(method="direct", volume_stiffness=10.0)
    )
    _check_bounded(head, r, hand, faces)
    with pytest.raises(ValueError, match="volume_stiffness"):
        PBDConfig(method="jacobi", volume_stiffness=1.0)
    with pytest.raises(ValueError, match="direct_outer"):
        PBDConfig(method="direct", direct_outer=0)
