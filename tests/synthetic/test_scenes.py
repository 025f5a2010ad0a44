"""The synthetic generator's scenes (SyntheticConfig.scene): interaction, no_contact, face_only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from trimesh.triangles import closest_point

from avatar.synthetic import SCENES, SyntheticCapture, SyntheticConfig, generate
from avatar.templates.layers import FLAMELayer, MANOLayer
from avatar.templates.procedural import procedural_hand, procedural_head
from data_schemas.params import PARAMS
from data_schemas.tables import read_table
from pipeline.cli import run_app
from stages.fit import ABSENT_HAND_DROP_M
from tests.conftest import compose_cfg

SMALL = dict(subject="synth_a", sequence="train", image_size=32, num_frames=6, num_cameras=4)
FLAME_KEYS = (
    "flame_shape",
    "flame_expression",
    "flame_global_orient",
    "flame_neck_pose",
    "flame_jaw_pose",
    "flame_eye_pose",
    "flame_transl",
)
MANO_KEYS = ("mano_shape", "mano_hand_pose", "mano_global_orient", "mano_transl")
HAND_LABEL, FACE_LABEL = 2, 1
#: The paper's interaction radius d_max is 0.05 m; no_contact keeps the hand beyond this.
NO_CONTACT_MIN_M = 0.06
#: ... and, while the script holds the hand at the face, this near.
NEAR_MAX_M = 0.15


@pytest.fixture(scope="module")
def captures() -> dict[str, SyntheticCapture]:
    """scene -> the small capture of that scene."""
    return {scene: generate(SyntheticConfig(**SMALL, scene=scene)) for scene in SCENES}


def _mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> float:
    """Smallest distance (metres) from ``points`` (N, 3) to the triangle mesh (``vertices`` (V, 3), ``faces``
    (F, 3)), exactly: a pair (point, triangle) at most d0 apart (d0 = the nearest point-vertex distance) has
    every triangle vertex within d0 + the longest edge of the point, so only those pairs are measured."""
    edge = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=-1).max()
    tree = cKDTree(vertices)
    nearest, _ = tree.query(points)
    reach = nearest.min() + edge
    near = np.flatnonzero(nearest <= reach)
    pairs = [
        (i, f)
        for i, verts in zip(near, tree.query_ball_point(points[near], reach))
        for f in np.flatnonzero(np.isin(faces, verts).any(axis=1))
    ]
    point_ids, face_ids = np.array(pairs).T
    closest = closest_point(vertices[faces[face_ids]], points[point_ids])
    return float(np.linalg.norm(closest - points[point_ids], axis=1).min())


def _hand_face_distances(cap: SyntheticCapture) -> np.ndarray:
    """(T,) smallest distance from a hand vertex to the undeformed face surface per frame, from the
    ground-truth parameters."""
    head, hand = procedural_head(), procedural_hand()
    flame = FLAMELayer.for_params(head, cap.params)
    face = flame(*(torch.as_tensor(cap.params[k]) for k in FLAME_KEYS)).vertices.numpy()
    hands = MANOLayer(hand)(*(torch.as_tensor(cap.params[k]) for k in MANO_KEYS)).vertices.numpy()
    return np.array([_mesh_distance(h, f, np.array(head.faces)) for h, f in zip(hands, face)])


def _assert_untouched(cap: SyntheticCapture) -> None:
    """No contact and zero soft-tissue offsets in every frame."""
    assert not cap.contact.any()
    assert not cap.face_offsets.any()


def test_interaction_is_the_default_and_unchanged(captures: dict[str, SyntheticCapture]) -> None:
    default = generate(SyntheticConfig(**SMALL))
    interaction = captures["interaction"]
    for cam in default.cameras:
        cid = cam.camera_id
        np.testing.assert_array_equal(interaction.frames[cid], default.frames[cid])
        np.testing.assert_array_equal(interaction.masks[cid], default.masks[cid])
        for part in ("hand", "face"):
            np.testing.assert_array_equal(interaction.keypoints[cid][part], default.keypoints[cid][part])
    for key, value in default.params.items():
        np.testing.assert_array_equal(interaction.params[key], value, err_msg=key)
    np.testing.assert_array_equal(interaction.face_offsets, default.face_offsets)
    np.testing.assert_array_equal(interaction.contact, default.contact)
    assert interaction.contact.any()


@pytest.mark.parametrize("scene", ["no_contact", "face_only"])
def test_same_head_motion_and_hand_articulation(captures: dict[str, SyntheticCapture], scene: str) -> None:
    for key in (*FLAME_KEYS, "mano_shape", "mano_hand_pose"):
        np.testing.assert_array_equal(captures[scene].params[key], captures["interaction"].params[key], err_msg=key)
    for key in MANO_KEYS:
        assert np.isfinite(captures[scene].params[key]).all(), key


def test_no_contact_holds_the_hand_near_the_face(captures: dict[str, SyntheticCapture]) -> None:
    cap = captures["no_contact"]
    _assert_untouched(cap)
    distance = _hand_face_distances(cap)
    assert (distance > NO_CONTACT_MIN_M).all(), distance
    # frames 1 .. T-2 (times 0.2 .. 0.8) are where the script holds the hand at the face
    assert (distance[1:-1] < NEAR_MAX_M).all(), distance
    for t in range(1, SMALL["num_frames"] - 1):
        assert sum((m[t] == HAND_LABEL).sum() > 10 for m in cap.masks.values()) >= 3, t


def test_face_only_shows_no_hand(captures: dict[str, SyntheticCapture]) -> None:
    cap = captures["face_only"]
    _assert_untouched(cap)
    assert (_hand_face_distances(cap) > 1.0).all()
    size = SMALL["image_size"]
    for cid, masks in cap.masks.items():
        assert not (masks == HAND_LABEL).any(), cid
        assert ((masks == FACE_LABEL).sum(axis=(1, 2)) > 0.05 * size * size).all(), cid
        assert not cap.keypoints[cid]["hand"][..., 2].any(), cid
        assert cap.keypoints[cid]["face"][..., 2].mean() > 0.5, cid


def test_unknown_scene_names_the_allowed_ones() -> None:
    with pytest.raises(ValueError, match="interaction.*no_contact.*face_only"):
        SyntheticConfig(**SMALL, scene="bogus")


def test_fit_of_a_face_only_capture_writes_a_placeholder_hand(tmp_path: Path) -> None:
    cfg = compose_cfg(
        [
            f"paths.outputs={tmp_path}",
            "quality=smoke",
            "run.until=fit",
            "run.progress=false",
            "fit.source=fitted",
            "dataset.scene=face_only",
            "stage.capture.cross_reenactment=false",
            "stage.capture.num_cameras=4",
            "quality.capture_size=48",
            "quality.num_frames_train=3",
            "quality.num_frames_test=2",
            "stage.fit.coarse_iterations=5",
            "stage.fit.fine_iterations=5",
        ]
    )
    run_app(cfg)
    fit_dir = tmp_path / "synth_a" / "fit"
    report = json.loads((fit_dir / "fit_report.json").read_text())
    for seq in ("train", "test"):
        entry = report["sequences"][seq]
        assert entry["hand_fitted"] is False
        assert "mpjpe_hand_mm" not in entry and "hand" not in entry["reprojection_px"]
        assert entry["mpjpe_face_mm"] < 10.0
        params = read_table(fit_dir / seq / "params.parquet", PARAMS)
        for key in MANO_KEYS[:3]:
            assert not np.asarray(params[key]).any(), key
        np.testing.assert_allclose(
            np.asarray(params["mano_transl"]), np.asarray(params["flame_transl"]) - [0.0, ABSENT_HAND_DROP_M, 0.0]
        )
