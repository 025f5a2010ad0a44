"""dataset=decaf on a tiny fake tree in the DECAF release layout (the dataset itself is licensed):
cameras, videos, masks, provided keypoints/params/deformations/contacts round-trip; every bad input
is one clear error and leaves no capture behind; keypoints detector=provided and fit.source=provided."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from avatar.templates import FLAMELayer, TemplateModel, load_official_model, procedural_hand, procedural_head
from data_schemas.cameras import read_cameras
from data_schemas.capture import CaptureIndex, mask_path, provided_path, video_path
from data_schemas.deform import CONTACTS, DEFORM
from data_schemas.images import read_png
from data_schemas.keypoints import KEYPOINTS
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.tables import read_table
from data_schemas.video import read_video, write_video
from importers.decaf import read_calibration
from pipeline.cli import run_app
from pipeline.config import ConfigError
from pipeline.runner import StageFailed
from tests.conftest import compose_cfg

W, H = 48, 40
CAMERAS = ("084", "100", "102")
FRAMES = {"train": 4, "test": 3}
FG = (slice(8, 36), slice(10, 40))  # rows, columns of the person in the mattes
HAND_BOX = (26, 8, 36, 18)  # u0, v0, u1, v1 of the hand keypoints


@pytest.fixture(autouse=True)
def _single_thread(one_torch_thread: None) -> None:
    """One torch thread per test (see tests/conftest.py)."""


# ---------------------------------------------------------------------------- fake tree
def _extrinsic(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.02 * i, 0.15 * (i - 1), 0.01]).as_matrix()
    T[:3, 3] = [0.01 * i, -0.02, 0.8]
    return T


def _intrinsic(i: int) -> np.ndarray:
    return np.array([[60.0 + i, 0.0, W / 2 + 0.5], [0.0, 61.0 + i, H / 2 - 0.5], [0.0, 0.0, 1.0]])


def _params(n: int, rng: np.random.Generator) -> dict:
    def head() -> dict:
        return {
            "shape_params": rng.normal(0, 0.5, 100),
            "expression_params": rng.normal(0, 0.5, 50),
            "pose_params": np.concatenate([rng.normal(0, 0.1, 3), [0.1, 0.0, 0.0]]),
            "global_orient": rng.normal(0, 0.3, 3),
            "transl": rng.normal(0, 0.05, 3),
        }

    def hand() -> dict:
        return {
            "betas": rng.normal(0, 0.5, (1, 10)),
            "hand_pose": rng.normal(0, 0.2, 45),
            "global_orient": rng.normal(0, 0.5, 3),
            "transl": [0.05, -0.02, 0.1],
        }

    return {t: {"head": head(), "right_hand": hand()} for t in range(n)}


def _dump(path: Path, obj: object, protocol: int = pickle.HIGHEST_PROTOCOL) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as stream:
        pickle.dump(obj, stream, protocol=protocol)


def _save(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, arr)


def make_decaf(root: Path, subject: str = "S1", head_vertices: int = 2562, keypoints: bool = True) -> Path:
    """A DECAF release with one subject: 3 cameras, 4 train and 3 test frames."""
    rng = np.random.default_rng(0)
    for mode, n in FRAMES.items():
        base = root / mode
        _dump(
            base / "cameras" / subject / "cameras.pkl",
            {cam: {"intrinsic": _intrinsic(i), "extrinsic": _extrinsic(i)} for i, cam in enumerate(CAMERAS)},
        )
        for i, cam in enumerate(CAMERAS):
            video = np.full((n, H, W, 3), 40 + 20 * i, np.uint8)
            video[:, FG[0], FG[1]] = (200, 150, 120)
            write_video(base / "videos" / subject / f"{cam}.mp4", video, 25.0)
            matte = np.zeros((n, H, W, 3), np.uint8)
            matte[:, FG[0], FG[1]] = 255
            write_video(base / "segmentations" / subject / f"{cam}.mp4", matte, 25.0)
            if keypoints:
                face = np.concatenate([rng.uniform([12, 10], [38, 34], (n, 68, 2)), np.zeros((n, 68, 1))], axis=-1)
                face[0, 5] = np.nan  # a failed landmark
                face[1, 6] = [W + 3, 10, 0]  # outside the image
                face[2] = 0.0  # no face found in this frame
                hand = rng.uniform(HAND_BOX[:2], HAND_BOX[2:], (n, 21, 2))
                _save(base / "head_keys" / subject / f"{cam}.npy", face)
                _save(base / "right_hand_keys" / subject / f"{cam}.npy", hand)
        _dump(base / "params" / subject / "params_smoothed.pkl", _params(n, rng))
        _save(base / "deformations" / subject / "deforms.npy", rng.normal(0, 1e-3, (n, head_vertices, 3)))
        touching = rng.random((n, head_vertices)) < 0.01 * np.arange(n)[:, None]  # none in frame 0
        _save(base / "contacts" / subject / "contacts_head.npy", touching)
        _save(base / "contacts" / subject / "contacts_rh.npy", rng.random((n, 778)) < 0.01)
    return root


def _official_pickles(tmp: Path) -> tuple[Path, Path]:
    """The procedural head and hand written as "official" FLAME 2020 / MANO pickles (300 identity +
    100 expression columns), so the conversion runs on a model of the official layout."""
    head, hand = procedural_head(), procedural_hand()
    ns = int(head.num_shape)
    shapedirs = np.zeros((head.num_vertices, 3, 400))
    shapedirs[:, :, :ns] = head.shapedirs[:, :, :ns]
    shapedirs[:, :, 300 : 300 + head.num_shapes_total - ns] = head.shapedirs[:, :, ns:]
    paths = tmp / "models" / "generic_model.pkl", tmp / "models" / "MANO_RIGHT.pkl"
    for model, path, extra in (
        (head, paths[0], {"shapedirs": shapedirs}),
        (
            hand,
            paths[1],
            {"hands_components": np.array(hand.hands_components), "hands_mean": np.array(hand.hands_mean)},
        ),
    ):
        _dump(
            path,
            {
                "v_template": np.array(model.v_template),
                "shapedirs": np.array(model.shapedirs),
                "posedirs": np.array(model.posedirs),
                "J_regressor": np.array(model.J_regressor),
                "weights": np.array(model.weights),
                "kintree_table": np.array(model.kintree_table),
                "f": np.array(model.faces),
                **extra,
            },
            protocol=2,
        )  # as the official files
    return paths


def _cfg(tmp_path: Path, *extra: str, until: str = "capture"):
    return compose_cfg(
        [
            "dataset=decaf",
            f"dataset.root={tmp_path / 'decaf'}",
            "subject=S1",
            f"paths.outputs={tmp_path / 'out'}",
            "run.progress=false",
            f"run.until={until}",
            *extra,
        ]
    )


def _models(tmp_path: Path) -> list[str]:
    flame, mano = _official_pickles(tmp_path)
    return [f"model.flame_path={flame}", f"model.mano_path={mano}"]


def _load(path: Path):
    with path.open("rb") as stream:
        return pickle.load(stream)


# ---------------------------------------------------------------------------- a good tree
def test_decaf_capture_round_trips(tmp_path):
    make_decaf(tmp_path / "decaf")
    run_app(_cfg(tmp_path, *_models(tmp_path)))
    cap, src = tmp_path / "out" / "S1" / "capture", tmp_path / "decaf"
    index = CaptureIndex.read(cap)
    assert index.dataset == "decaf"
    assert {k: v.num_frames for k, v in index.sequences.items()} == FRAMES
    for info in index.sequences.values():
        assert info.provided == ("keypoints", "params", "deform", "contacts"), info.notes
        assert info.has_masks and not info.has_ground_truth and (info.width, info.height) == (W, H)

    # cameras: K and world-to-camera as given; a point projects where DECAF's P = K [R|t] puts it
    cams = {c.camera_id: c for c in read_cameras(cap / "cameras.parquet")}
    assert sorted(cams) == list(CAMERAS) and [cams[c].split for c in CAMERAS] == ["train", "train", "test"]
    point = np.array([0.03, -0.01, 0.05])
    for i, cam in enumerate(CAMERAS):
        np.testing.assert_array_equal(cams[cam].K, _intrinsic(i))
        np.testing.assert_array_equal(cams[cam].world_to_cam, _extrinsic(i))
        proj = (_intrinsic(i) @ _extrinsic(i)[:3]) @ np.append(point, 1.0)
        np.testing.assert_allclose(cams[cam].project(point)[0], proj[:2] / proj[2], atol=1e-9)

    for seq, n in FRAMES.items():
        # videos and masks: every frame, labels 0 background / 1 face / 2 hand
        for cam in CAMERAS:
            assert read_video(video_path(cap, seq, cam)).shape == (n, H, W, 3)
            for t in range(n):
                labels = read_png(mask_path(cap, seq, cam, t), 1)
                assert set(np.unique(labels)) == {0, 1, 2}
                assert labels[2, 2] == 0 and labels[30, 14] == 1 and labels[13, 31] == 2
                assert (labels[:6] == 0).all() and (labels[:, :8] == 0).all()
        # keypoints: pixels as shipped, confidence 0 for failed, outside and missing detections
        table = read_table(provided_path(cap, seq, "keypoints"), KEYPOINTS)
        assert len(table["frame"]) == n * len(CAMERAS) * 2
        for frame, cam, part, uvc in zip(table["frame"], table["camera_id"], table["part"], table["uvc"]):
            uvc = np.reshape(uvc, (-1, 3))
            shipped = np.load(src / seq / ("head_keys" if part == "face" else "right_hand_keys") / "S1" / f"{cam}.npy")
            ok = uvc[:, 2] > 0
            np.testing.assert_allclose(uvc[ok, :2], shipped[frame][ok, :2], atol=1e-4)
            expect_missing = {0: [5], 1: [6], 2: list(range(68))}.get(frame, []) if part == "face" else []
            assert sorted(np.flatnonzero(~ok)) == expect_missing
        # params: MANO as shipped; FLAME reposed about the root joint gives DECAF's centroid-pivot mesh
        shipped = _load(src / seq / "params" / "S1" / "params_smoothed.pkl")
        params = read_table(provided_path(cap, seq, "params"), PARAMS)
        np.testing.assert_allclose(
            params["mano_hand_pose"], [shipped[t]["right_hand"]["hand_pose"] for t in range(n)], atol=1e-6
        )
        np.testing.assert_allclose(
            params["mano_shape"], [shipped[t]["right_hand"]["betas"][0] for t in range(n)], atol=1e-6
        )
        np.testing.assert_allclose(
            params["flame_jaw_pose"], [shipped[t]["head"]["pose_params"][3:] for t in range(n)], atol=1e-6
        )
        _assert_same_head(params, shipped, load_official_model(tmp_path / "models" / "generic_model.pkl", "flame"))
        # deformations: world offsets = -R_global d; contacts as flags
        deform = read_table(provided_path(cap, seq, "deform"), DEFORM)
        d = np.load(src / seq / "deformations" / "S1" / "deforms.npy")
        for t in range(n):
            R = Rotation.from_rotvec(shipped[t]["head"]["global_orient"]).as_matrix()
            np.testing.assert_allclose(deform["offsets"][t].reshape(-1, 3), -(d[t] @ R.T), atol=1e-7)
        contacts = read_table(provided_path(cap, seq, "contacts"), CONTACTS)
        head_contacts = np.load(src / seq / "contacts" / "S1" / "contacts_head.npy")
        np.testing.assert_array_equal(contacts["face"], head_contacts.astype(np.float32))
        np.testing.assert_array_equal(contacts["contact"], head_contacts.any(axis=1))
        np.testing.assert_array_equal(deform["contact"], head_contacts.any(axis=1))


def _assert_same_head(params: dict, shipped: dict, head: TemplateModel) -> None:
    """Our FLAMELayer on the converted params == DECAF's forward: FLAME with root pose, then a rotation
    about the vertex centroid plus transl (its FLAME_util.flame_forwarding)."""
    n = len(params["frame"])
    get = lambda key: torch.tensor(np.array([shipped[t]["head"][key] for t in range(n)]))  # noqa: E731
    layer = FLAMELayer(head, num_shape=100, num_expression=50)
    with torch.no_grad():
        pose = get("pose_params")
        v_f = layer(
            get("shape_params"), get("expression_params"), global_orient=pose[:, :3], jaw_pose=pose[:, 3:]
        ).vertices.numpy()
        ours = layer(
            *(
                torch.tensor(np.asarray(params[k], np.float64))
                for k in (
                    "flame_shape",
                    "flame_expression",
                    "flame_global_orient",
                    "flame_neck_pose",
                    "flame_jaw_pose",
                    "flame_eye_pose",
                    "flame_transl",
                )
            )
        ).vertices.numpy()
    R = Rotation.from_rotvec(get("global_orient").numpy()).as_matrix()
    centre = v_f.mean(axis=1, keepdims=True)
    decaf = np.einsum("tij,tvj->tvi", R, v_f - centre) + centre + get("transl").numpy()[:, None]
    np.testing.assert_allclose(ours, decaf, atol=2e-6)  # float32 in the table: ~1e-7 m rounding


def test_frame_step_reencodes_and_selects_every_table(tmp_path):
    make_decaf(tmp_path / "decaf")
    run_app(_cfg(tmp_path, "dataset.frame_step=2", "dataset.max_frames=1", 'dataset.test_cameras=["084"]'))
    cap = tmp_path / "out" / "S1" / "capture"
    index = CaptureIndex.read(cap)
    assert {k: v.num_frames for k, v in index.sequences.items()} == {"train": 1, "test": 1}
    assert index.sequences["train"].frame_rate == pytest.approx(12.5)
    assert [c.split for c in read_cameras(cap / "cameras.parquet")] == ["test", "train", "train"]
    assert read_video(video_path(cap, "test", "100")).shape[0] == 1
    # without the official models no params (and a note why); deformations that fit the configured
    # (here procedural) head model still come in
    info = index.sequences["train"]
    assert info.provided == ("keypoints", "deform", "contacts")
    assert any("params_smoothed.pkl not imported" in note and "model.flame_path" in note for note in info.notes)
    table = read_table(provided_path(cap, "train", "keypoints"), KEYPOINTS)
    assert set(table["frame"]) == {0}


def test_deformations_that_do_not_fit_the_head_model_are_skipped_with_a_note(tmp_path):
    make_decaf(tmp_path / "decaf", head_vertices=5023)
    run_app(_cfg(tmp_path, *_models(tmp_path)))
    info = CaptureIndex.read(tmp_path / "out" / "S1" / "capture").sequences["train"]
    assert "deform" not in info.provided and "params" in info.provided
    assert any("deforms.npy not imported: 5023 vertices, but the official head model has 2562" in n for n in info.notes)


# ---------------------------------------------------------------------------- keypoints and fit
def test_provided_keypoints_and_params_flow_through_keypoints_and_fit(tmp_path):
    make_decaf(tmp_path / "decaf")
    run_app(_cfg(tmp_path, *_models(tmp_path), "stage.keypoints.detector=provided", "fit.source=provided", until="fit"))
    out = tmp_path / "out" / "S1"
    for seq in FRAMES:
        kp = read_table(out / "keypoints" / seq / "keypoints.parquet", KEYPOINTS)
        shipped = read_table(provided_path(out / "capture", seq, "keypoints"), KEYPOINTS)
        assert kp["camera_id"] == shipped["camera_id"] and kp["part"] == shipped["part"]
        np.testing.assert_array_equal(np.concatenate(kp["uvc"]), np.concatenate(shipped["uvc"]))
        fitted = read_table(out / "fit" / seq / "params.parquet", PARAMS)
        provided = read_table(provided_path(out / "capture", seq, "params"), PARAMS)
        for k in PARAM_COLUMNS:
            np.testing.assert_array_equal(fitted[k], provided[k])
    assert json.loads((out / "fit" / "fit_report.json").read_text())["source"] == "provided"


def test_provided_keypoints_missing_names_the_dataset(tmp_path):
    make_decaf(tmp_path / "decaf", keypoints=False)
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path, "stage.keypoints.detector=provided", until="keypoints"))
    assert (
        "detector=provided needs keypoints shipped with the dataset (dataset=decaf), but the 'decaf' capture "
        "of 'S1' has none" in str(info.value)
    )


def test_provided_params_without_official_models_say_what_to_set(tmp_path):
    make_decaf(tmp_path / "decaf")
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path, "stage.keypoints.detector=provided", "fit.source=provided", until="fit"))
    message = str(info.value)
    assert "fit.source=provided needs parameters shipped with the dataset" in message
    assert "set model.flame_path (FLAME 2020 generic_model.pkl) and model.mano_path (MANO_RIGHT.pkl)" in message
    assert not (tmp_path / "out" / "S1" / "fit").exists()


# ---------------------------------------------------------------------------- bad input
def _expect_capture_error(tmp_path: Path, fragment: str, *extra: str) -> None:
    with pytest.raises(StageFailed) as info:
        run_app(_cfg(tmp_path, *extra))
    assert fragment in str(info.value), str(info.value)
    assert not (tmp_path / "out" / "S1" / "capture").exists(), "half-written capture left behind"


def test_cameras_pkl_of_protocol_2_written_by_python_3_is_read(tmp_path):
    """Python 3 stores an array's bytes in a protocol-2 pickle through _codecs.encode: legitimate, read it."""
    root = make_decaf(tmp_path / "decaf")
    cameras = {cam: {"intrinsic": _intrinsic(i), "extrinsic": _extrinsic(i)} for i, cam in enumerate(CAMERAS)}
    path = root / "train" / "cameras" / "S1" / "cameras.pkl"
    _dump(path, cameras, protocol=2)
    assert b"_codecs" in path.read_bytes()
    calibration = read_calibration(path)
    for i, cam in enumerate(CAMERAS):
        np.testing.assert_array_equal(calibration[str(cam)]["K"], _intrinsic(i))
        np.testing.assert_array_equal(calibration[str(cam)]["world_to_cam"], _extrinsic(i))


def test_missing_cameras_pkl(tmp_path):
    root = make_decaf(tmp_path / "decaf")
    (root / "test" / "cameras" / "S1" / "cameras.pkl").unlink()
    _expect_capture_error(tmp_path, "test/cameras/S1/cameras.pkl: missing")


def test_video_without_camera(tmp_path):
    root = make_decaf(tmp_path / "decaf")
    videos = root / "train" / "videos" / "S1"
    (videos / "111.mp4").write_bytes((videos / "084.mp4").read_bytes())
    _expect_capture_error(tmp_path, "111.mp4: video has no camera '111' in")


def test_views_disagree_on_frame_count(tmp_path):
    root = make_decaf(tmp_path / "decaf")
    write_video(root / "train" / "videos" / "S1" / "100.mp4", np.zeros((6, H, W, 3), np.uint8), 25.0)
    _expect_capture_error(tmp_path, "views disagree on frame count")


def test_params_for_other_frames(tmp_path):
    root = make_decaf(tmp_path / "decaf")
    path = root / "train" / "params" / "S1" / "params_smoothed.pkl"
    params = _load(path)
    params[4] = params[3]
    _dump(path, params)
    _expect_capture_error(tmp_path, "params_smoothed.pkl: 5 frames, but the videos of train/S1 have 4")


@pytest.mark.parametrize(
    "damage, fragment",
    [
        (lambda p: p[2]["right_hand"].pop("hand_pose"), "frame 2 lacks right_hand.hand_pose"),
        (lambda p: p[1]["head"].update(pose_params=np.zeros(3)), "frame 1 head.pose_params has shape (3,), expected 6"),
        (lambda p: p[0]["head"].update(transl=[0.0, np.nan, 0.0]), "frame 0 head.transl contains NaN"),
    ],
    ids=["missing-key", "wrong-width", "nan"],
)
def test_malformed_params(tmp_path, damage, fragment):
    root = make_decaf(tmp_path / "decaf")
    path = root / "train" / "params" / "S1" / "params_smoothed.pkl"
    params = _load(path)
    damage(params)
    _dump(path, params)
    _expect_capture_error(tmp_path, fragment)


def test_keypoints_of_the_wrong_shape(tmp_path):
    root = make_decaf(tmp_path / "decaf")
    _save(root / "test" / "head_keys" / "S1" / "100.npy", np.zeros((3, 51, 2)))
    _expect_capture_error(tmp_path, "head_keys/S1/100.npy: shape (3, 51, 2), expected (3, 68, 2 or more)")


def test_missing_subject_lists_those_on_disk_before_any_stage(tmp_path):
    make_decaf(tmp_path / "decaf", subject="S3")
    with pytest.raises(ConfigError) as info:
        run_app(_cfg(tmp_path, "run.dry=true"))
    assert (
        "train/videos/S1: missing; set dataset.root to the unpacked DecafDataset folder and subject to one of ['S3']"
        in str(info.value)
    )
