"""Look at a capture before modelling it: is the hand in view, does it come within the interaction radius
of the face, which face triangles can it deform, and therefore which parts and modules to model.

The paper's interaction weight w_i = (cos(pi d / d_max) + 1) / 2 vanishes beyond d_max (0.05 m), so a
recording in which the hand never comes that close gives the interaction MLPs nothing to learn and PBD
nothing to resolve; a recording without a hand needs no MANO Gaussians and no hand MLPs.

Distances are from every face vertex to the nearest hand vertex (a k-d tree per frame): an upper bound
of the surface distance by at most half a hand edge (~2-4 mm on MANO), far below d_max.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

#: The decisions a scene analysis takes, each ``auto`` (decided from the capture), ``true`` or ``false``.
DECISIONS = ("model_hand", "model_pbd", "model_interaction")


def hand_face_distances(face_vertices: np.ndarray, hand_vertices: np.ndarray) -> np.ndarray:
    """(T, V) distance of every face vertex to the nearest hand vertex, per frame.

    Args:
        face_vertices: (T, V, 3) posed face meshes, metres.
        hand_vertices: (T, H, 3) posed hand meshes, metres.
    """
    return np.stack([cKDTree(hand).query(face)[0] for face, hand in zip(face_vertices, hand_vertices)])


@dataclass(frozen=True)
class SceneFacts:
    """What one sequence shows, per frame (T frames).

    Attributes:
        hand_views: (T,) int, cameras in which the hand covers at least the minimum area.
        hand_present: (T,) bool, the hand is seen in at least the minimum number of cameras.
        distance_m: (T,) float, smallest face-vertex-to-hand distance; NaN where the hand is not present.
        contact: (T,) bool, hand present and within d_max of the face.
        near_vertices: (T, V) bool, face vertices within d_max of the hand in contact frames.
    """

    hand_views: np.ndarray
    hand_present: np.ndarray
    distance_m: np.ndarray
    contact: np.ndarray
    near_vertices: np.ndarray


def scene_facts(hand_views: np.ndarray, distances: np.ndarray, min_views: int, d_max: float) -> SceneFacts:
    """Per-frame facts from the hand's per-frame camera count (T,) and the (T, V) face-to-hand distances."""
    hand_views = np.asarray(hand_views, dtype=np.int64)
    present = hand_views >= min_views
    nearest = distances.min(axis=1)
    contact = present & (nearest < d_max)
    return SceneFacts(
        hand_views=hand_views,
        hand_present=present,
        distance_m=np.where(present, nearest, np.nan),
        contact=contact,
        near_vertices=(distances < d_max) & contact[:, None],
    )


def deforming_triangles(near_vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool: face triangles with a vertex within d_max of the hand in some contact frame, from the
    (T, V) ``near_vertices`` of :class:`SceneFacts` and the (F, 3) face triangles."""
    return np.asarray(near_vertices.any(axis=0))[faces].any(axis=1)


@dataclass(frozen=True)
class SceneDecision:
    """What to model, and why: ``why`` maps each of :data:`DECISIONS` to one sentence."""

    model_hand: bool
    model_pbd: bool
    model_interaction: bool
    why: dict[str, str] = field(default_factory=dict)

    @property
    def reasons(self) -> list[str]:
        """The sentences in decision order."""
        return [self.why[name] for name in DECISIONS if name in self.why]


def decide(facts: SceneFacts, min_hand_fraction: float, overrides: dict[str, str]) -> SceneDecision:
    """The decisions from the training sequence's facts; ``overrides`` maps each of :data:`DECISIONS`
    to ``auto``, ``true`` or ``false`` (the user's word wins, and the reason says so)."""
    bad = {k: v for k, v in overrides.items() if k not in DECISIONS or v not in ("auto", "true", "false")}
    if bad or set(overrides) != set(DECISIONS):
        raise ValueError(f"scene overrides {overrides}: need exactly {DECISIONS}, each auto, true or false")
    T = len(facts.hand_present)
    hand_frames, contact_frames = int(facts.hand_present.sum()), int(facts.contact.sum())
    reasons: dict[str, str] = {}

    def settle(name: str, auto: bool, why: str) -> bool:
        if overrides[name] == "auto":
            reasons[name] = why
            return auto
        forced = overrides[name] == "true"
        reasons[name] = (
            f"{name}={str(forced).lower()} set in the config (stage.scene.{name}); "
            f"the capture alone would give {str(auto).lower()}: {why}"
        )
        return forced

    hand_auto = T > 0 and hand_frames >= min_hand_fraction * T
    model_hand = settle(
        "model_hand",
        hand_auto,
        f"hand in view in {hand_frames} of {T} frames: "
        + (
            "hand modelled (MANO Gaussians, hand MLPs)"
            if hand_auto
            else "no hand model (face-only avatar: no MANO Gaussians, no hand MLPs)"
        ),
    )
    touching = model_hand and contact_frames > 0
    if not model_hand:
        why = "no hand modelled: no contact to simulate or learn"
    elif not hand_frames:
        why = "the hand is never in view: no contact seen"
    elif contact_frames:
        why = f"hand within d_max of the face in {contact_frames} of {T} frames"
    else:
        why = f"the hand never comes within d_max of the face (closest {np.nanmin(facts.distance_m) * 1e3:.0f} mm)"
    model_pbd = settle("model_pbd", touching, why + (": PBD simulated" if touching else ": PBD skipped"))
    model_interaction = settle(
        "model_interaction",
        touching,
        why + (": interaction MLPs on the deforming triangles" if touching else ": interaction module skipped"),
    )
    return SceneDecision(model_hand, model_pbd, model_interaction, reasons)
