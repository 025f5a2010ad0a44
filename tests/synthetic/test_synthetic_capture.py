"""End-to-end tests of the synthetic capture generator (small resolutions)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_erosion

from avatar.geometry.winding import winding_number
from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate
from avatar.synthetic.geometry import closest_points
from avatar.synthetic.shading import BACKGROUND_LINEAR, srgb_encode
from avatar.templates.layers import FLAMELayer, MANOLayer
from avatar.templates.procedural import procedural_hand, procedural_head

SIZE, FRAMES = 40, 6
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


@pytest.fixture(scope="module")
def train_a() -> SyntheticCapture:
    return generate(SyntheticConfig("synth_a", "train", SIZE, FRAMES))


@pytest.fixture(scope="module")
def test_a() -> SyntheticCapture:
    return generate(SyntheticConfig("synth_a", "test", 24, FRAMES, num_cameras=2))


@pytest.fixture(scope="module")
def train_b() -> SyntheticCapture:
    return generate(SyntheticConfig("synth_b", "train", SIZE, 2, num_cameras=8))


def _mano(cap: SyntheticCapture) -> tuple[MANOLayer, torch.Tensor, torch.Tensor]:
    layer = MANOLayer(procedural_hand())
    out = layer(*(torch.as_tensor(cap.params[k]) for k in MANO_KEYS))
    return layer, out.vertices, out.joints


def _faces_final(cap: SyntheticCapture) -> torch.Tensor:
    head = procedural_head()
    layer = FLAMELayer.for_params(head, cap.params)
    verts = layer(*(torch.as_tensor(cap.params[k]) for k in FLAME_KEYS)).vertices
    return verts + torch.as_tensor(cap.face_offsets)


def test_generation_is_deterministic() -> None:
    cfg = SyntheticConfig("synth_b", "test", 24, 2, num_cameras=2, seed=3)
    a, b = generate(cfg), generate(cfg)
    for cam in a.cameras:
        cid = cam.camera_id
        assert np.array_equal(a.frames[cid], b.frames[cid])
        assert np.array_equal(a.masks[cid], b.masks[cid])
        for part in ("hand", "face"):
            assert np.array_equal(a.keypoints[cid][part], b.keypoints[cid][part])
    for key in a.params:
        assert np.array_equal(a.params[key], b.params[key])
    assert np.array_equal(a.face_offsets, b.face_offsets) and np.array_equal(a.contact, b.contact)


def test_shapes_and_dtypes(train_a: SyntheticCapture) -> None:
    cap, t = train_a, FRAMES
    assert len(cap.cameras) == 8 and [c.split for c in cap.cameras].count("test") == 1
    for cam in cap.cameras:
        assert (cam.width, cam.height) == (SIZE, SIZE)
        assert cam.K.shape == (3, 3) and cam.K.dtype == np.float64
        assert cam.world_to_cam.shape == (4, 4) and cam.world_to_cam.dtype == np.float64
        assert cam.dist.shape == (5,) and cam.split in ("train", "test")
        frames, masks = cap.frames[cam.camera_id], cap.masks[cam.camera_id]
        assert frames.shape == (t, SIZE, SIZE, 3) and frames.dtype == np.uint8
        assert masks.shape == (t, SIZE, SIZE) and masks.dtype == np.uint8
        assert set(np.unique(masks)) <= {0, 1, 2}
        kp = cap.keypoints[cam.camera_id]
        assert kp["hand"].shape == (t, 21, 3) and kp["face"].shape == (t, 68, 3)
        assert set(np.unique(kp["hand"][..., 2])) <= {0.0, 1.0}
    widths = {
        "flame_global_orient": 3,
        "flame_neck_pose": 3,
        "flame_jaw_pose": 3,
        "flame_eye_pose": 6,
        "flame_transl": 3,
        "mano_shape": 10,
        "mano_hand_pose": 45,
        "mano_global_orient": 3,
        "mano_transl": 3,
    }
    assert set(cap.params) == set(FLAME_KEYS) | set(MANO_KEYS)
    for key, value in cap.params.items():
        assert value.ndim == 2 and value.shape[0] == t and np.isfinite(value).all()
        if key in widths:
            assert value.shape[1] == widths[key], key
    v_face = procedural_head().num_vertices
    assert cap.face_offsets.shape == (t, v_face, 3) and np.isfinite(cap.face_offsets).all()
    assert cap.contact.shape == (t,) and cap.contact.dtype == bool and cap.frame_rate > 0


def test_plain_background(train_a: SyntheticCapture) -> None:
    grey = int(srgb_encode(np.array(BACKGROUND_LINEAR)))
    for cid, frames in train_a.frames.items():
        # Background away from silhouette edges (antialiased pixels blend in the foreground).
        background = binary_erosion(train_a.masks[cid] == 0, structure=np.ones((1, 3, 3)))
        assert background.any() and (frames[background] == grey).all()


def test_masks_and_contact(train_a: SyntheticCapture) -> None:
    cap = train_a
    assert cap.contact.any() and not cap.contact.all()
    assert not cap.contact[0] and not cap.contact[-1]
    for t in range(FRAMES):
        for cid in cap.masks:
            assert (cap.masks[cid][t] == 1).sum() > 0.05 * SIZE * SIZE
        with_hand = sum((m[t] == 2).sum() > 10 for m in cap.masks.values())
        if cap.contact[t]:
            assert with_hand >= 6
    moved = np.abs(cap.face_offsets).reshape(FRAMES, -1).max(axis=1)
    assert (moved[cap.contact] > 5e-4).all()
    assert (moved[~cap.contact] == 0).all()


def test_face_does_not_penetrate_the_hand(train_a: SyntheticCapture) -> None:
    layer, hand, _ = _mano(train_a)
    faces = torch.from_numpy(np.array(layer.model.faces))
    face = _faces_final(train_a)
    worst = 0.0
    for t in np.flatnonzero(train_a.contact):
        lo, hi = hand[t].amin(0) - 0.005, hand[t].amax(0) + 0.005
        near = face[t][((face[t] > lo) & (face[t] < hi)).all(dim=1)]
        inside = winding_number(near, hand[t], faces) > 0.5
        if inside.any():
            _, depth, _ = closest_points(near[inside], hand[t], faces, candidates=faces.shape[0])
            worst = max(worst, float(depth.max()))
    assert worst < 1.5e-3


def test_keypoints_reproject_and_mostly_lie_in_the_image(train_a: SyntheticCapture) -> None:
    layer, verts, joints = _mano(train_a)
    hand_kp = layer.keypoints21(verts, joints).numpy()  # (T, 21, 3) world
    good_views = 0
    for cam in train_a.cameras:
        stored = train_a.keypoints[cam.camera_id]["hand"]
        pc = hand_kp @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
        uv = (pc[..., :2] / pc[..., 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2]
        np.testing.assert_allclose(stored[..., :2], uv, atol=1e-6)
        in_image = ((uv >= 0) & (uv < SIZE)).all(axis=-1)
        good_views += in_image[train_a.contact].mean() > 0.9
        face = train_a.keypoints[cam.camera_id]["face"]
        assert ((face[..., :2] >= 0) & (face[..., :2] < SIZE)).all(axis=-1).mean() > 0.95
        # Visible keypoints are inside the image; some in-image ones are occluded.
        assert in_image[stored[..., 2] == 1].all()
    assert good_views >= 6
    vis = np.concatenate([k["hand"][..., 2].ravel() for k in train_a.keypoints.values()])
    in_img = np.concatenate(
        [
            (((k["hand"][..., :2] >= 0) & (k["hand"][..., :2] < SIZE)).all(-1)).ravel()
            for k in train_a.keypoints.values()
        ]
    )
    assert 0.1 < vis.mean() < 0.95 and (in_img & (vis == 0)).any()


def test_train_and_test_motions_differ(train_a: SyntheticCapture, test_a: SyntheticCapture) -> None:
    for key in ("mano_transl", "mano_hand_pose", "flame_neck_pose"):
        assert np.abs(train_a.params[key] - test_a.params[key]).max() > 0.01, key
    assert test_a.contact.any() and not test_a.contact.all()


def test_identities_differ(train_a: SyntheticCapture, train_b: SyntheticCapture) -> None:
    for key in ("flame_shape", "mano_shape"):
        assert np.abs(train_a.params[key][0] - train_b.params[key][0]).max() > 0.1
    cid = train_a.cameras[3].camera_id
    skin_a = train_a.frames[cid][0][train_a.masks[cid][0] == 1].mean(axis=0)
    skin_b = train_b.frames[cid][0][train_b.masks[cid][0] == 1].mean(axis=0)
    assert np.abs(skin_a - skin_b).max() > 20
