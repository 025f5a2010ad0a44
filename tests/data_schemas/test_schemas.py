"""Artifact schemas: round trips, and one clear error for every kind of bad file."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import trimesh

from data_schemas.cameras import Camera, read_cameras, write_cameras
from data_schemas.gaussians_ply import SH_C0, GaussianCloud, read_gaussians_ply, write_gaussians_ply
from data_schemas.images import read_exr, read_png, write_exr, write_png
from data_schemas.keypoints import KEYPOINTS
from data_schemas.params import PARAMS
from data_schemas.tables import Column, SchemaError, TableSchema, read_table, write_table

RNG = np.random.default_rng(0)


def _camera(cid: str = "cam00", **kw) -> Camera:
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0, 0, 0.8]
    args = dict(camera_id=cid, width=64, height=64, K=K, world_to_cam=T, dist=np.zeros(5), split="train")
    args.update(kw)
    return Camera(**args)


def _params(n: int = 3) -> dict:
    widths = {
        "flame_shape": 10,
        "flame_expression": 10,
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
    data = {k: RNG.normal(size=(n, w)).astype(np.float32) for k, w in widths.items()}
    data["frame"] = np.arange(n)
    return data


def test_params_round_trip_with_metadata(tmp_path):
    data = _params()
    path = tmp_path / "params.parquet"
    write_table(path, PARAMS, data)
    back = read_table(path, PARAMS)
    for k, v in data.items():
        np.testing.assert_array_equal(back[k], v)
    meta = pq.read_schema(path).metadata
    assert meta[b"schema_version"] == b"1" and meta[b"artifact"] == b"params"
    assert json.loads(meta[b"units"])["mano_transl"] == "m"
    assert pq.ParquetFile(path).metadata.row_group(0).column(0).compression == "ZSTD"
    assert pq.read_schema(path).field("mano_hand_pose").type == pa.list_(pa.float32(), 45)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("mano_transl"), "missing ['mano_transl']"),
        (
            lambda d: d.__setitem__("mano_hand_pose", np.zeros((3, 44))),
            "column 'mano_hand_pose': expected vectors of length 45",
        ),
        (
            lambda d: d["flame_transl"].__setitem__((1, 2), np.nan),
            "column 'flame_transl': contains NaN or Inf in rows [1]",
        ),
        (lambda d: d.__setitem__("mano_transl", np.zeros((4, 3))), "column 'mano_transl': expected 3 rows"),
    ],
)
def test_bad_table_data_names_file_and_column(tmp_path, mutate, message):
    data = _params()
    mutate(data)
    path = tmp_path / "params.parquet"
    with pytest.raises(SchemaError) as info:
        write_table(path, PARAMS, data)
    assert str(path) in str(info.value) and message in str(info.value)
    assert not path.exists()


def test_reading_the_wrong_or_an_old_table_is_refused(tmp_path):
    path = tmp_path / "kp.parquet"
    write_table(
        path, KEYPOINTS, {"frame": np.array([0]), "camera_id": ["c"], "part": ["hand"], "uvc": [np.ones((21, 3))]}
    )
    with pytest.raises(SchemaError, match="expected a 'params' table, found 'keypoints'"):
        read_table(path, PARAMS)
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    meta[b"schema_version"] = b"0"
    pq.write_table(table.replace_schema_metadata(meta), path)
    with pytest.raises(SchemaError, match="schema_version 0 != supported 1"):
        read_table(path, KEYPOINTS)
    path.write_bytes(b"garbage")
    with pytest.raises(SchemaError, match="not a readable Parquet file"):
        read_table(path, KEYPOINTS)


def test_nan_written_by_another_tool_is_caught_on_read(tmp_path):
    path = tmp_path / "params.parquet"
    write_table(path, PARAMS, _params())
    table = pq.read_table(path)
    col = table.column("flame_transl").combine_chunks()
    values = col.flatten().to_numpy().copy()
    values[4] = np.nan
    bad = pa.FixedSizeListArray.from_arrays(pa.array(values), 3)
    table = table.set_column(table.schema.get_field_index("flame_transl"), table.schema.field("flame_transl"), bad)
    pq.write_table(table, path)
    with pytest.raises(SchemaError, match=r"column 'flame_transl' contains NaN or Inf in frames \[1\]$"):
        read_table(path, PARAMS)  # values[4]: the second frame's y


def test_values_that_are_not_finite_are_named_by_frame_or_row(tmp_path):
    """Read back, a per-frame table names the frames (its ``frame`` column) that hold NaN or Inf, the first five and
    how many; a table without frames names the rows; a variable-length list column the same."""
    data = _params()
    data["frame"] = np.array([10, 11, 12])
    path = tmp_path / "params.parquet"
    write_table(path, PARAMS, data)
    table = pq.read_table(path)
    values = table.column("mano_hand_pose").combine_chunks().flatten().to_numpy().copy()
    values[[45, 46, 2 * 45]] = [np.inf, np.nan, -np.inf]  # frames 11 (twice) and 12
    bad = pa.FixedSizeListArray.from_arrays(pa.array(values), 45)
    index = table.schema.get_field_index("mano_hand_pose")
    pq.write_table(table.set_column(index, table.schema.field("mano_hand_pose"), bad), path)
    with pytest.raises(SchemaError, match=r"column 'mano_hand_pose' contains NaN or Inf in frames \[11, 12\]$"):
        read_table(path, PARAMS)
    ragged = TableSchema("ragged", 1, (Column("values", "list_f32"),))
    rows = [[0.0], [1.0, np.nan], [], [np.inf]] + [[float("nan")]] * 6
    write_table(tmp_path / "r.parquet", ragged, {"values": [[0.0]] * len(rows)})
    table = pq.read_table(tmp_path / "r.parquet")
    column = pa.array(rows, pa.list_(pa.float32()))
    pq.write_table(table.set_column(0, table.schema.field("values"), column), tmp_path / "r.parquet")
    with pytest.raises(SchemaError, match=r"contains NaN or Inf in rows \[1, 3, 4, 5, 6\] \(8 in all\)$"):
        read_table(tmp_path / "r.parquet", ragged)


def test_cameras_round_trip_and_projection(tmp_path):
    cams = [_camera("cam00"), _camera("cam01", split="test")]
    write_cameras(tmp_path / "cameras.parquet", cams)
    back = read_cameras(tmp_path / "cameras.parquet")
    assert [c.camera_id for c in back] == ["cam00", "cam01"] and back[1].split == "test"
    np.testing.assert_array_equal(back[0].K, cams[0].K)
    # A point on the optical axis projects to the principal point.
    np.testing.assert_allclose(back[0].project(np.array([[0.0, 0.0, 0.2]]))[0], [[32.0, 32.0]])


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        (_camera(K=np.zeros((3, 3))), "K is singular"),
        (_camera(K=np.full((3, 3), np.nan)), "K must be a finite 3x3 matrix"),
        (_camera(world_to_cam=np.diag([1.0, 1, -1, 1])), "not a rigid transform"),
        (_camera(split="val"), "split must be one of"),
    ],
)
def test_bad_cameras_are_refused_with_the_camera_named(tmp_path, camera, message):
    with pytest.raises(SchemaError) as info:
        write_cameras(tmp_path / "cameras.parquet", [camera])
    assert "camera 'cam00'" in str(info.value) and message in str(info.value)


def test_exr_round_trip_including_strided_input(tmp_path):
    rgb = RNG.random((5, 14, 3), dtype=np.float32)[:, ::2]  # strided view: must still be written right
    depth = RNG.random((5, 7), dtype=np.float32)
    write_exr(tmp_path / "x.exr", {"RGB": rgb, "depth": depth})
    back = read_exr(tmp_path / "x.exr")
    np.testing.assert_array_equal(back["RGB"], rgb)
    np.testing.assert_array_equal(back["depth"], depth)
    with pytest.raises(SchemaError, match="must be float32 or float16"):
        write_exr(tmp_path / "y.exr", {"depth": depth.astype(np.float64)})
    with pytest.raises(SchemaError, match="missing EXR"):
        read_exr(tmp_path / "nope.exr")


def test_png_round_trip_keeps_rgb_order(tmp_path):
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # pure red must stay red (not become blue through OpenCV's BGR)
    write_png(tmp_path / "r.png", img)
    np.testing.assert_array_equal(read_png(tmp_path / "r.png", 3), img)
    mask = (RNG.random((4, 5)) > 0.5).astype(np.uint8) * 2
    write_png(tmp_path / "m.png", mask)
    np.testing.assert_array_equal(read_png(tmp_path / "m.png", 1), mask)
    with pytest.raises(SchemaError, match="unreadable PNG"):
        read_png(tmp_path / "missing.png", 3)


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_gaussian_ply_round_trip_and_independent_reader(tmp_path, sh_degree):
    n = 50
    rgb = RNG.random((n, 3))
    cloud = GaussianCloud.from_rgb(
        RNG.normal(size=(n, 3)),
        RNG.normal(size=(n, 3)) - 4,
        RNG.normal(size=(n, 4)),
        RNG.normal(size=n),
        rgb,
        sh_degree=sh_degree,
    )
    cloud.sh_rest[:] = RNG.normal(size=cloud.sh_rest.shape)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, cloud)
    back = read_gaussians_ply(path)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
        np.testing.assert_allclose(getattr(back, name), getattr(cloud, name), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(back.rgb(), rgb, atol=1e-6)
    # An independent PLY parser sees the standard 3DGS property names and values.
    raw = trimesh.load(path, process=False).metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(raw["x"], cloud.means[:, 0], rtol=1e-6)
    np.testing.assert_allclose(raw["f_dc_1"], (rgb[:, 1] - 0.5) / SH_C0, rtol=1e-5)
    np.testing.assert_allclose(raw["rot_0"], cloud.quats[:, 0], rtol=1e-6)
    assert (f"f_rest_{3 * ((sh_degree + 1) ** 2 - 1) - 1}" in raw.dtype.names) == (sh_degree > 0)


def test_gaussian_ply_refuses_nan_and_truncation(tmp_path):
    cloud = GaussianCloud.from_rgb(
        np.zeros((2, 3)), np.zeros((2, 3)), np.array([[1.0, 0, 0, 0]] * 2), np.zeros(2), np.full((2, 3), 0.5)
    )
    cloud.means[0, 0] = np.nan
    with pytest.raises(SchemaError, match="NaN"):
        write_gaussians_ply(tmp_path / "g.ply", cloud)
    cloud.means[0, 0] = 0
    write_gaussians_ply(tmp_path / "g.ply", cloud)
    raw = (tmp_path / "g.ply").read_bytes()
    (tmp_path / "g.ply").write_bytes(raw[:-4])
    with pytest.raises(SchemaError, match="truncated"):
        read_gaussians_ply(tmp_path / "g.ply")
