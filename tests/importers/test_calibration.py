"""COLMAP and nerfstudio calibrations -> cameras: round trips through files the tests write, projections
checked against pycolmap's own camera models and against the OpenGL projection formula, and every bad
input one clear error."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from avatar.calibration.undistort import Undistorter
from data_schemas.tables import SchemaError
from importers.calibrated_images import CalibratedImage, camera_id_of, rig_cameras
from importers.colmap import OPENCV_MODELS, find_model, read_colmap
from importers.nerfstudio import OPENGL_TO_OPENCV, read_transforms

W, H = 64, 48
POINTS = np.array([[0.02, -0.01, 0.05], [-0.03, 0.02, -0.04], [0.0, 0.0, 0.0], [0.04, 0.03, 0.02]])
# model -> parameters (COLMAP's order), mild distortion
MODELS = {
    "SIMPLE_PINHOLE": [70.0, 32.5, 24.5],
    "PINHOLE": [70.0, 72.0, 31.5, 23.5],
    "SIMPLE_RADIAL": [70.0, 32.0, 24.0, 0.05],
    "RADIAL": [70.0, 32.0, 24.0, 0.05, -0.02],
    "OPENCV": [70.0, 71.0, 32.0, 24.0, 0.04, -0.01, 0.002, -0.001],
    "FULL_OPENCV": [70.0, 71.0, 32.0, 24.0, 0.04, -0.01, 0.002, -0.001, 0.003, 0.01, -0.005, 0.002],
}


def _pose(i: int) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera rotation (3, 3) and translation (3,) of camera i, looking at the origin from 0.4 units."""
    angle = 0.3 * (i - 2)
    R_look = np.array([[np.cos(angle), 0.0, -np.sin(angle)], [0.0, 1.0, 0.0], [np.sin(angle), 0.0, np.cos(angle)]])
    return R_look, np.array([0.01 * i, -0.005, 0.4])


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(R)[0].ravel()
    angle = np.linalg.norm(rvec)
    axis = rvec / angle if angle > 0 else np.array([1.0, 0.0, 0.0])
    return np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])


def write_colmap(folder: Path, models: dict[str, list[float]], names: list[str], text: bool = False) -> None:
    """A COLMAP model with one camera per entry of ``models`` and one image (named by ``names``) each."""
    rec = pycolmap.Reconstruction()
    for i, ((model, params), name) in enumerate(zip(models.items(), names, strict=True)):
        camera = pycolmap.Camera.create_from_model_name(i + 1, model, 70.0, W, H)
        camera.params = params
        rec.add_camera_with_trivial_rig(camera)
        R, t = _pose(i)
        pose = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(_quat_xyzw(R)), translation=t)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1), pose)
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write)(str(folder))


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_colmap_cameras_project_as_pycolmap_does(tmp_path, text):
    names = ["cam00.png", "cam01/000000.png", "cam02.jpg", "cam03/f.png", "cam04.png", "cam05.png"]
    write_colmap(tmp_path / "sparse" / "0", MODELS, names, text=text)
    model = find_model(tmp_path)
    assert model == tmp_path / "sparse" / "0"
    images = read_colmap(model)
    assert [camera_id_of(i.name) for i in images] == [f"cam{i:02d}" for i in range(6)]
    reference = pycolmap.Reconstruction(str(model))
    for image, ref_image in zip(images, sorted(reference.images.values(), key=lambda i: i.name), strict=True):
        ref_camera = reference.cameras[ref_image.camera_id]
        in_cam = (image.world_to_cam[:3, :3] @ POINTS.T).T + image.world_to_cam[:3, 3]
        expected = ref_camera.img_from_cam(in_cam) - 0.5  # COLMAP's pixel centres sit at +0.5
        rvec = cv2.Rodrigues(image.world_to_cam[:3, :3])[0]
        ours = cv2.projectPoints(POINTS, rvec, image.world_to_cam[:3, 3], image.K, image.dist)[0][:, 0]
        np.testing.assert_allclose(ours, expected, atol=1e-9, err_msg=ref_camera.model.name)


def test_rig_cameras_scale_translations_and_hold_out_the_last_camera(tmp_path):
    write_colmap(
        tmp_path, {k: MODELS[k] for k in ("PINHOLE", "OPENCV", "FULL_OPENCV")}, ["cam00.png", "cam01.png", "cam02.png"]
    )
    images = read_colmap(tmp_path)
    cameras = rig_cameras(images, "model", scale_m=0.25, test_cameras=None)
    assert [c.split for c in cameras] == ["train", "train", "test"]
    assert {len(c.dist) for c in cameras} == {8}  # padded to the longest: OpenCV reads zeros the same
    for cam, image in zip(cameras, images, strict=True):
        scaled_points = POINTS * 0.25
        np.testing.assert_allclose(cam.project(scaled_points)[0], _pinhole(image, POINTS), atol=1e-9)
        np.testing.assert_allclose(cam.world_to_cam[:3, 3], image.world_to_cam[:3, 3] * 0.25)
    chosen = rig_cameras(images, "model", scale_m=1.0, test_cameras=["cam00"])
    assert [c.split for c in chosen] == ["test", "train", "train"]


def _pinhole(image: CalibratedImage, points: np.ndarray) -> np.ndarray:
    cam = (image.world_to_cam[:3, :3] @ points.T).T + image.world_to_cam[:3, 3]
    uvw = (image.K @ cam.T).T
    return uvw[:, :2] / uvw[:, 2:]


def test_colmap_model_opencv_cannot_express_is_one_clear_error(tmp_path):
    write_colmap(
        tmp_path,
        {"PINHOLE": MODELS["PINHOLE"], "OPENCV_FISHEYE": [70.0, 70.0, 32.0, 24.0, 0.1, 0, 0, 0]},
        ["cam00.png", "cam01.png"],
    )
    with pytest.raises(SchemaError, match=r"OPENCV_FISHEYE model.*colmap image_undistorter"):
        read_colmap(tmp_path)
    assert set(OPENCV_MODELS) == set(MODELS)


def test_unreadable_colmap_model_names_the_folder(tmp_path):
    (tmp_path / "cameras.txt").write_text("# not really\n1 PINHOLE abc\n")
    (tmp_path / "images.txt").write_text("")
    (tmp_path / "points3D.txt").write_text("")
    with pytest.raises(SchemaError, match="not a readable COLMAP model"):
        read_colmap(tmp_path)


def _transforms(K: np.ndarray, world_to_cam: list[np.ndarray], names: list[str], **extra: object) -> dict:
    """A nerfstudio transforms.json for OpenCV cameras: pixel centres at +0.5, camera-to-world in OpenGL axes."""
    frames = [
        {"file_path": f"images/{n}", "transform_matrix": (np.linalg.inv(T) @ OPENGL_TO_OPENCV).tolist()}
        for n, T in zip(names, world_to_cam, strict=True)
    ]
    return {
        "camera_model": "OPENCV",
        "fl_x": K[0, 0],
        "fl_y": K[1, 1],
        "cx": K[0, 2] + 0.5,
        "cy": K[1, 2] + 0.5,
        "w": W,
        "h": H,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
        **extra,
    }


def _world_to_cam(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _pose(i)
    return T


def test_nerfstudio_axes_match_the_opengl_projection(tmp_path):
    K = np.array([[70.0, 0.0, 31.2], [0.0, 72.0, 23.7], [0.0, 0.0, 1.0]])
    data = _transforms(K, [_world_to_cam(i) for i in range(3)], ["cam00.png", "cam01.png", "cam02.png"])
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    cameras = rig_cameras(read_transforms(tmp_path / "transforms.json"), "t", 1.0, None)
    for cam, frame in zip(cameras, data["frames"], strict=True):
        # The other way: OpenGL camera (looks down -z, y up), nerfstudio's continuous pixel coordinates.
        cam_gl = (np.linalg.inv(np.asarray(frame["transform_matrix"])) @ np.c_[POINTS, np.ones(4)].T).T
        depth = -cam_gl[:, 2]
        u = data["fl_x"] * cam_gl[:, 0] / depth + data["cx"]
        v = -data["fl_y"] * cam_gl[:, 1] / depth + data["cy"]
        uv, z = cam.project(POINTS)
        np.testing.assert_allclose(uv, np.c_[u, v] - 0.5, atol=1e-9)
        np.testing.assert_allclose(z, depth, atol=1e-12)


def test_nerfstudio_per_frame_intrinsics_override_the_shared_ones(tmp_path):
    K = np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 23.5], [0.0, 0.0, 1.0]])
    data = _transforms(K, [_world_to_cam(0), _world_to_cam(1)], ["a.png", "b.png"])
    data["frames"][1].update({"fl_x": 90.0, "fl_y": 91.0, "k1": 0.03})
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    a, b = read_transforms(tmp_path / "transforms.json")
    assert a.K[0, 0] == 70.0 and b.K[0, 0] == 90.0 and b.K[1, 1] == 91.0
    np.testing.assert_array_equal(b.dist, [0.03, 0, 0, 0, 0])


@pytest.mark.parametrize(
    ("damage", "fragment"),
    [
        (lambda d: d["frames"][1].update({"w": W + 2}), "the sizes must agree"),
        (lambda d: d["frames"][0].update({"transform_matrix": [[float("nan")] * 4] * 4}), "finite 4x4"),
        (lambda d: d["frames"][0].update({"transform_matrix": (2 * np.eye(4)).tolist()}), "not a rigid transform"),
        (lambda d: d.update({"camera_model": "OPENCV_FISHEYE"}), "not a pinhole model"),
        (lambda d: d.update({"k4": 0.01}), "k4 (an r^8 radial term)"),
        (lambda d: d.pop("fl_x"), "intrinsics ['fl_x']"),
        (lambda d: d.update({"frames": []}), "non-empty 'frames'"),
    ],
    ids=["sizes", "nan-pose", "scaled-pose", "fisheye", "k4", "no-focal", "no-frames"],
)
def test_bad_transforms_json_is_one_clear_error(tmp_path, damage, fragment):
    K = np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 23.5], [0.0, 0.0, 1.0]])
    data = _transforms(K, [_world_to_cam(0), _world_to_cam(0)], ["cam00/0.png", "cam00/1.png"])
    damage(data)
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SchemaError, match=re.escape(fragment)) as info:
        read_transforms(tmp_path / "transforms.json")
    assert "transforms.json" in str(info.value)


def test_rig_checks_name_the_calibration():
    K = np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 23.5], [0.0, 0.0, 1.0]])
    still = [
        CalibratedImage("cam00/0.png", W, H, K, np.zeros(4), _world_to_cam(0)),
        CalibratedImage("cam01/0.png", W, H, K, np.zeros(4), _world_to_cam(1)),
    ]
    moved = CalibratedImage("cam00/1.png", W, H, K, np.zeros(4), _world_to_cam(2))
    with pytest.raises(SchemaError, match="'cam00/0.png' and 'cam00/1.png' belong to camera 'cam00'"):
        rig_cameras([*still, moved], "model", 1.0, None)
    bad = CalibratedImage("cam02.png", W, H, K, np.zeros(4), np.full((4, 4), np.inf))
    with pytest.raises(SchemaError, match="model: image 'cam02.png' has non-finite pose"):
        rig_cameras([*still, bad], "model", 1.0, None)
    with pytest.raises(SchemaError, match=r"test_cameras=\['cam09'\]: choose some but not all"):
        rig_cameras(still, "model", 1.0, ["cam09"])
    with pytest.raises(SchemaError, match="positive number of metres"):
        rig_cameras(still, "model", float("nan"), None)


def test_undistortion_moves_a_point_to_its_pinhole_projection():
    """A bright dot drawn where the distorted camera sees a point lands, after undistortion, where the
    pinhole camera with the same K projects it (to a fraction of a pixel)."""
    K = np.array([[60.0, 0.0, 40.0], [0.0, 60.0, 30.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.3, 0.05, 0.002, -0.001, 0.0])
    point = np.array([[0.5, 0.38, 1.0]])  # near the corner, where distortion moves pixels most
    distorted = cv2.projectPoints(point, np.zeros(3), np.zeros(3), K, dist)[0][0, 0]
    pinhole = (K @ point[0])[:2]
    assert np.linalg.norm(distorted - pinhole) > 3.0  # the test means something
    yy, xx = np.mgrid[0:60, 0:80]
    blob = np.exp(-((xx - distorted[0]) ** 2 + (yy - distorted[1]) ** 2) / (2 * 1.2**2))
    image = np.repeat((blob * 255).round().astype(np.uint8)[..., None], 3, axis=-1)
    out = Undistorter(K, dist, 80, 60).image(image)[..., 0].astype(np.float64)
    centroid = np.array([(out * xx).sum(), (out * yy).sum()]) / out.sum()
    np.testing.assert_allclose(centroid, pinhole, atol=0.35)
    labels = Undistorter(K, dist, 80, 60).labels((blob > 0.5).astype(np.uint8) * 3)
    assert set(np.unique(labels)) <= {0, 3} and labels.any()
