"""Scene analysis: what a capture shows (hand in view, contact, deforming triangles) and what to model."""

from avatar.scene.analysis import (
    DECISIONS,
    SceneDecision,
    SceneFacts,
    decide,
    deforming_triangles,
    hand_face_distances,
    scene_facts,
)

__all__ = [
    "DECISIONS",
    "SceneDecision",
    "SceneFacts",
    "decide",
    "deforming_triangles",
    "hand_face_distances",
    "scene_facts",
]
