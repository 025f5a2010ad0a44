"""``interactavatar-export`` on a tiny trained model (the DAG up to stage two at 32 px, 4 steps each, and the reenact
stage driven by a params.parquet file): every file read back with ``plyfile`` as the standard 3DGS layout, each frame
the Gaussians the pipeline poses for it (evaluate's posing of a motion of the fit, reenact's of a driver file), the
axis conversions against their closed form, and the errors: one line, no traceback, nothing written. What a hostile
user tried is refused: an --overwrite of a folder no export wrote, a destination inside a subject's outputs, a run the
pipeline would retrain (its fit republished), a run another run is writing, absurd frames, templates, drivers,
methods and seeds; Ctrl-C while the command starts and SIGTERM while it writes leave nothing behind."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData
from scipy.spatial.transform import Rotation

import pipeline.export_ply
import pipeline.export_ply.frames
from avatar.artifacts import load_face_offsets, load_params, method_params, read_params, write_params
from avatar.artifacts.motion import applied_deformation, load_sequence
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.posing import MeshSequence, posed_meshes
from avatar.render.gaussians import WorldGaussians
from avatar.representations import TrainedAvatar, load_trained
from avatar.templates import procedural_hand, procedural_head
from avatar.threads import single_threaded
from data_schemas.gaussians_ply import SH_C0
from data_schemas.writes import WriteError
from pipeline.cli import run_app
from pipeline.export_ply import main
from pipeline.manifest import read_manifest, verify_outputs
from pipeline.workspace import Artifact, Workspace
from stages import REGISTRY
from tests.conftest import REPO, cli_env, compose_cfg, default_sigint, wait_for

TINY = [
    "quality=smoke",
    "quality.capture_size=32",
    "quality.image_size=32",
    "quality.supersample=1",
    "quality.num_frames_train=3",
    "quality.num_frames_test=4",  # the hand touches the face in frame 1 of the held-out motion
    "quality.warmup_steps=4",
    "quality.dynamic_steps=4",
    "stage.capture.num_cameras=2",
    "stage.capture.cross_reenactment=false",
    "fit.source=ground_truth",
    "run.progress=false",
]
#: the 3DGS reference implementation's vertex properties for degree-0 colours (no f_rest_*), in its order
LAYOUT = [
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread: None) -> None:
    """The exporter poses with torch's threads as it finds them, and the results change in the last bit with their
    number: the fixture's stages, the exporter and the references here all run on one thread."""


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the subject folder of a trained tiny model whose reenact stage was driven by a file, that file)."""
    out = tmp_path_factory.mktemp("export")
    with single_threaded():
        run_app(compose_cfg([f"paths.outputs={out}", *TINY, "run.until=dynamic"]))
        driver = out / "driver" / "params.parquet"
        driver.parent.mkdir()
        shutil.copy(out / "synth_a" / "fit" / "test" / "params.parquet", driver)
        run_app(compose_cfg([f"paths.outputs={out}", *TINY, "run.only=reenact", f"reenact.driver={driver}"]))
    return out / "synth_a", driver


def _dynamic(subject: Path) -> Path:
    return subject / "methods" / "interactavatar" / "dynamic"


def _vertices(path: Path) -> dict[str, np.ndarray]:
    """The vertex columns of a PLY read with plyfile, after checking it is the standard 3DGS layout."""
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<" and [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == LAYOUT
    assert {p.val_dtype for p in vertex.properties} == {"f4"}
    return {name: np.asarray(vertex[name]) for name in LAYOUT}


def _columns(v: dict[str, np.ndarray], prefix: str, n: int) -> np.ndarray:
    return np.stack([v[f"{prefix}{i}"] for i in range(n)], -1)


def _assert_is(v: dict[str, np.ndarray], g: object) -> None:
    """The file's columns are the posed Gaussians ``g``: the same positions bit for bit, log-scales, logit opacities,
    the quaternions made unit, degree-0 colours, zero normals."""
    means, scales, quats, opacities, colors = (
        getattr(g, k).numpy() for k in ("means", "scales", "quats", "opacities", "colors")
    )
    assert len(v["x"]) == len(means)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], -1), means)
    np.testing.assert_array_equal(np.stack([v["nx"], v["ny"], v["nz"]], -1), 0)
    np.testing.assert_allclose(np.exp(_columns(v, "scale_", 3)), scales, rtol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-v["opacity"])), opacities.clip(1e-6, 1 - 1e-6), atol=1e-6)
    rot = _columns(v, "rot_", 4)
    np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(rot, quats / np.linalg.norm(quats, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(0.5 + SH_C0 * _columns(v, "f_dc_", 3), colors, atol=1e-6)


def _pose(model: TrainedAvatar, meshes: MeshSequence, cond: SequenceConditioning, t: int) -> WorldGaussians:
    with torch.no_grad():
        return model.pose(cond, meshes.vertices[t], t)


def test_every_frame_of_the_held_out_motion_is_3dgs_posed_as_evaluate_poses_it(trained, tmp_path, capsys) -> None:
    subject, _ = trained
    out = tmp_path / "held_out"
    assert main([str(subject), "--motion", "test", "--out", str(out)]) == 0
    assert capsys.readouterr().err.count("\n") == 4  # a line per frame
    assert sorted(p.name for p in out.iterdir()) == [f"{t:05d}.ply" for t in range(4)] + ["export.json"]
    # evaluate's posing, with the run's own config: the fit's parameters, the pbd stage's contact offsets
    cfg, fit, dynamic = compose_cfg(TINY), subject / "fit", _dynamic(subject)
    params = method_params(dynamic, fit, "test")
    meshes, cond = load_sequence(fit, "test", cfg, pbd_dir=applied_deformation(cfg, subject / "pbd"), params=params)
    undeformed, _ = load_sequence(fit, "test", cfg, pbd_dir=None, params=params)
    model = load_trained(dynamic)
    offsets = load_face_offsets(subject / "pbd", "test", 4, procedural_head().num_vertices)
    dented = [t for t in range(4) if np.abs(offsets[t]).max() > 1e-4]
    assert dented, "no contact in the held-out motion: the test would not see the deformation"
    for t in range(4):
        v = _vertices(out / f"{t:05d}.ply")
        _assert_is(v, _pose(model, meshes, cond, t))
        if t in dented:  # the contact deformation is baked in
            bare = _pose(model, undeformed, cond, t).means.numpy()
            assert np.abs(np.stack([v["x"], v["y"], v["z"]], -1) - bare).max() > 1e-4


def test_a_training_frame_is_stage_twos_own_ply_and_a_driver_file_is_the_reenactment(trained, tmp_path) -> None:
    subject, driver = trained
    assert main([str(subject), "--motion", "train", "--frames", "0", "--out", str(tmp_path / "train"), "--quiet"]) == 0
    assert main([str(subject), "--motion", str(driver), "--out", str(tmp_path / "driven"), "--quiet"]) == 0
    pairs = [(tmp_path / "train" / "00000.ply", _dynamic(subject) / "ply" / "train_0.ply")]
    reenacted = sorted((subject / "methods" / "interactavatar" / "reenact" / "ply").glob("*.ply"))
    assert [p.name for p in reenacted] == sorted(p.name for p in (tmp_path / "driven").glob("*.ply"))
    pairs += [(tmp_path / "driven" / p.name, p) for p in reenacted]
    for exported, pipelines in pairs:
        ours, theirs = _vertices(exported), _vertices(pipelines)
        for name in LAYOUT[:13]:  # all but the rotations: the same bytes
            np.testing.assert_array_equal(ours[name], theirs[name], err_msg=f"{exported.name}: {name}")
        rot = _columns(theirs, "rot_", 4)
        np.testing.assert_allclose(_columns(ours, "rot_", 4), rot / np.linalg.norm(rot, axis=1, keepdims=True), 1e-6)


def test_the_axes_are_the_closed_form_of_the_fitted_head(trained, tmp_path) -> None:
    subject, _ = trained
    files = {}
    for axes in ("world", "opengl", "opencv"):
        assert main([str(subject), "--frames", "1", "--axes", axes, "--out", str(tmp_path / axes), "--quiet"]) == 0
        files[axes] = _vertices(tmp_path / axes / "00001.ply")
    first = {k: v[:1] for k, v in load_params(subject / "fit", "train").items()}
    R0 = Rotation.from_rotvec(first["flame_global_orient"][0].astype(np.float64)).as_matrix()
    head = procedural_head()
    c0 = posed_meshes(first, head, procedural_hand()).vertices[0, : head.num_vertices].double().numpy().mean(0)
    world = files["world"]
    p = np.stack([world["x"], world["y"], world["z"]], -1).astype(np.float64)
    q = _columns(world, "rot_", 4)
    for axes, A in (("opengl", R0.T), ("opencv", np.diag([1.0, -1.0, -1.0]) @ R0.T)):
        v = files[axes]
        np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], -1), (p - c0) @ A.T, atol=2e-7)
        file_rotations = Rotation.from_quat(_columns(v, "rot_", 4)[:, [1, 2, 3, 0]]).as_matrix()
        world_rotations = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
        np.testing.assert_allclose(file_rotations, A @ world_rotations, atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(_columns(v, "rot_", 4), axis=1), 1, atol=1e-6)
        for name in ("opacity", "scale_0", "scale_1", "scale_2", "f_dc_0", "f_dc_1", "f_dc_2"):
            np.testing.assert_array_equal(v[name], world[name])
        info = json.loads((tmp_path / axes / "export.json").read_text())
        np.testing.assert_allclose(np.asarray(info["world_to_file"])[:3], np.c_[A, -A @ c0], atol=1e-12)


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], expected: str, code: int = 2) -> str:
    assert main(argv) == code
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if not line.startswith("frame ")]
    assert len(lines) == 1 and "Traceback" not in err and lines[0].startswith("interactavatar-export: "), err
    assert expected in lines[0], lines[0]
    return lines[0]


def test_each_mistake_is_one_line_that_names_the_fix_and_writes_nothing(trained, tmp_path, capsys) -> None:
    subject, _ = trained
    out = tmp_path / "out"
    empty = tmp_path / "alice"
    empty.mkdir()
    line = _one_line_error(capsys, [str(empty), "--out", str(out)], "no trained model of method 'interactavatar'")
    assert f"interactavatar paths.outputs={tmp_path} subject=alice method=interactavatar run.until=dynamic" in line
    line = _one_line_error(capsys, [str(subject), "--seed", "2", "--out", str(out)], "trained here: interactavatar")
    assert "seed=2 run.until=dynamic" in line
    _one_line_error(capsys, [str(subject.parent), "--out", str(out)], f"give one, e.g. {subject}")
    _one_line_error(capsys, [str(subject), "--motion", "tset", "--out", str(out)], "motions (test, train)")
    _one_line_error(capsys, [str(subject), "--motion", str(tmp_path / "x.parquet"), "--out", str(out)], "no such")
    _one_line_error(capsys, [str(subject), "--frames", "2-4", "--out", str(out)], "frame 4 out of range; motion 'test'")
    _one_line_error(capsys, [str(subject), "--frames", "1,x", "--out", str(out)], "frames and ranges such as")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    _one_line_error(capsys, [str(subject), "--out", str(blocker / "ply")], f"{blocker} is not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "alice"]
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    _one_line_error(capsys, [str(subject), "--out", str(tmp_path / "mine")], "exists; pass --overwrite")
    _one_line_error(capsys, [str(subject), "--out", str(tmp_path / "mine"), "--overwrite"], "no export.json")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


@pytest.mark.parametrize("failure", ["full disk", "ctrl-c"])
def test_a_failed_export_leaves_the_earlier_one_and_no_partial_folder(trained, tmp_path, monkeypatch, capsys, failure):
    subject, _ = trained
    out = tmp_path / "clip"
    assert main([str(subject), "--frames", "0", "--out", str(out), "--quiet"]) == 0
    before = (out / "00000.ply").read_bytes()
    original, written = pipeline.export_ply.frames.write_frame_ply, []

    def failing_write(path: Path, g: WorldGaussians) -> None:  # the second frame fails
        if written:
            raise KeyboardInterrupt if failure == "ctrl-c" else WriteError(f"{path}: No space left on device", 28)
        written.append(path)
        original(path, g)

    monkeypatch.setattr(pipeline.export_ply.frames, "write_frame_ply", failing_write)
    argv = [str(subject), "--frames", "1-3", "--out", str(out), "--overwrite", "--quiet"]
    if failure == "ctrl-c":
        _one_line_error(capsys, argv, f"interrupted; nothing written to {out}", code=130)
    else:
        line = _one_line_error(capsys, argv, f"--out {out}: no space left on its disk")
        assert "paths.outputs" not in line and "--out on a larger disk" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip"]  # no partial folder beside it
    assert sorted(p.name for p in out.iterdir()) == ["00000.ply", "export.json"]
    assert (out / "00000.ply").read_bytes() == before


def test_the_command_is_installed_and_its_help_states_the_axes_and_the_layout(capsys) -> None:
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["interactavatar-export"] == "pipeline.export_ply:main"
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for words in (
        "y up, the subject facing +z",
        "(x, y, z) -> (x, -y, -z)",
        "x y z nx ny nz f_dc_0",
        "unit quaternion",
    ):
        assert words in " ".join(text.split()), words
    assert "`" not in text


def test_a_device_this_machine_lacks_is_one_error_before_anything_is_read(tmp_path: Path, capsys) -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    status = pipeline.export_ply.main([str(tmp_path / "synth_a"), "--out", str(tmp_path / "x"), "--device", "cuda"])
    said = capsys.readouterr().err
    assert status == 2 and said.startswith("interactavatar-export: --device cuda: this machine has no CUDA device")
    assert not (tmp_path / "x").exists()


def test_the_export_poses_in_the_precision_training_used(tmp_path: Path) -> None:
    from pipeline.manifest import MANIFEST_NAME

    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"device": {"kind": "cuda", "precision": "bf16"}}))
    assert pipeline.export_ply.frames.trained_precision(tmp_path) == "bf16"
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"metrics": {}}))  # written before the device was recorded
    assert pipeline.export_ply.frames.trained_precision(tmp_path) == "fp32"


def _copy_subject(subject: Path, outputs: Path) -> Path:
    """A copy of the trained subject's folder in the outputs folder ``outputs``, for a test that changes it."""
    copy = outputs / subject.name
    shutil.copytree(subject, copy, ignore=shutil.ignore_patterns(".locks"))
    return copy


def test_overwrite_replaces_only_a_folder_an_earlier_export_wrote(trained, tmp_path, capsys) -> None:
    subject, _ = trained
    mine = tmp_path / "mine"
    mine.mkdir()
    for name in ("scan.ply", "00000.ply"):  # PLY files of the user's own, no export's record
        (mine / name).write_bytes(b"the user's")
    line = _one_line_error(capsys, [str(subject), "--out", str(mine), "--overwrite", "--quiet"], f"--out {mine}: ")
    assert "export.json" in line and "choose another --out" in line
    assert {p.name: p.read_bytes() for p in mine.iterdir()} == {"scan.ply": b"the user's", "00000.ply": b"the user's"}
    out = tmp_path / "clip"
    assert main([str(subject), "--frames", "0", "--out", str(out), "--quiet"]) == 0
    (out / "extra.ply").write_bytes(b"the user's")  # a file the export's record does not list
    _one_line_error(capsys, [str(subject), "--frames", "1", "--out", str(out), "--overwrite"], "extra.ply")
    assert (out / "extra.ply").read_bytes() == b"the user's"
    (out / "extra.ply").unlink()
    assert main([str(subject), "--frames", "1", "--out", str(out), "--overwrite", "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["00001.ply", "export.json"]


def test_a_destination_inside_a_subjects_outputs_is_refused(trained, tmp_path, capsys) -> None:
    subject, _ = trained
    dynamic = _dynamic(subject)
    link = tmp_path / "link"
    link.symlink_to(dynamic, target_is_directory=True)
    for out, extra in (
        (dynamic / "ply", ["--overwrite"]),  # stage two's own PLY folder
        (dynamic / "more", []),  # a new folder in an artifact
        (subject / "exports", []),
        (link / "more", []),  # the same through a link
    ):
        argv = [str(subject), "--frames", "0", "--out", str(out), *extra, "--quiet"]
        line = _one_line_error(capsys, argv, f"--out {out}: inside {subject.resolve()}")
        assert "choose a folder outside it" in line
    manifest = read_manifest(dynamic)
    assert manifest is not None and verify_outputs(dynamic, manifest, REGISTRY["dynamic"].outputs) is None


def test_an_export_waits_for_no_run_writing_what_it_reads_and_records_what_it_read(
    trained, tmp_path, capsys, monkeypatch
) -> None:
    subject, driver = trained
    monkeypatch.setattr(pipeline.export_ply, "LOCK_WAIT_S", 0.2, raising=False)
    ws = Workspace(subject.parent, subject.name)
    out = tmp_path / "clip"
    with ws.lock(Artifact("pbd"), [], REGISTRY.names(), 1.0):  # a run rewriting the pbd stage's offsets now
        line = _one_line_error(capsys, [str(subject), "--frames", "0", "--out", str(out)], "stage 'pbd'")
    assert "which is writing it; export again once that run has finished" in line and not out.exists()
    assert main([str(subject), "--motion", str(driver), "--frames", "0", "--out", str(out), "--quiet"]) == 0
    info = json.loads((out / "export.json").read_text())
    read = {"fit": "fit", "scene": "scene", "pbd": "pbd", "dynamic@interactavatar": "methods/interactavatar/dynamic"}
    assert info["read"] == {name: read_manifest(subject / folder).output_digest for name, folder in read.items()}
    assert info["motion_sha256"] == hashlib.sha256(driver.read_bytes()).hexdigest()


def test_an_avatar_trained_on_an_earlier_fit_is_refused_with_the_command_that_retrains_it(
    trained, tmp_path, capsys
) -> None:
    subject = _copy_subject(trained[0], tmp_path / "outputs")
    refit = [f"paths.outputs={subject.parent}", *TINY, "fit.source=fitted"]
    with single_threaded():
        run_app(compose_cfg([*refit, "run.until=fit"]))  # the fit republished from another source
        plan = run_app(compose_cfg([*refit, "run.until=dynamic", "run.dry=true"]))
    stale = [r.stage for r in plan if r.action == "would run"]
    assert stale == ["scene", "pbd", "warmup", "dynamic"]
    capsys.readouterr()
    out = tmp_path / "clip"
    line = _one_line_error(capsys, [str(subject), "--frames", "0", "--out", str(out)], "fit.source=fitted")
    assert f"interactavatar paths.outputs={subject.parent} subject=synth_a method=interactavatar" in line
    assert "run.until=dynamic" in line and all(stage in line for stage in stale), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outputs"]


def test_hostile_frames_templates_and_drivers_are_one_line_each(trained, tmp_path, capsys) -> None:
    subject, driver = trained
    out = tmp_path / "out"
    _one_line_error(capsys, [str(subject), "--frames", "0-99999999999999999", "--out", str(out)], "out of range")
    not_a_model = tmp_path / "hostname"
    not_a_model.write_text("a-machine\n")
    line = _one_line_error(capsys, [str(subject), "--flame-path", str(not_a_model), "--out", str(out)], "--flame-path")
    assert "model.flame_path=" not in line
    absurd = tmp_path / "absurd" / "params.parquet"
    params = read_params(driver)
    params["flame_transl"] = np.full_like(params["flame_transl"], 1e30)
    absurd.parent.mkdir()
    write_params(absurd, params)
    line = _one_line_error(capsys, [str(subject), "--motion", str(absurd), "--out", str(out)], f"--motion {absurd}: ")
    assert "'flame_transl'" in line and "fix or drop" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["absurd", "hostname"]


def test_a_method_or_seed_the_pipeline_refuses_is_refused_without_a_training_command(trained, tmp_path, capsys) -> None:
    subject, _ = trained
    out = tmp_path / "out"
    line = _one_line_error(capsys, [str(subject), "--method", "nosuch", "--out", str(out)], "--method nosuch: ")
    assert "method=nosuch" not in line and "gaussian_avatars" in line  # the methods there are
    line = _one_line_error(capsys, [str(subject), "--seed", "-1", "--out", str(out)], "--seed -1: ")
    assert "seed=-1" not in line
    # a method is a folder's name: '..' cannot reach the model of another outputs folder
    other = _copy_subject(subject, tmp_path / "other")
    shutil.rmtree(other / "methods")
    sneaky = os.path.relpath(subject / "methods" / "interactavatar", other / "methods")
    _one_line_error(capsys, [str(other), "--method", sneaky, "--out", str(out)], f"--method {sneaky}: ")
    assert not out.exists()


SLOW_EXPORT = """\
import sys, time
import data_schemas.gaussians_ply as ply
write = ply.write_gaussians_ply
ply.write_gaussians_ply = lambda *args: (time.sleep(1.0), write(*args))[1]
from pipeline.export_ply import main
sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_leaves_no_partial_folder_and_the_next_export_clears_one_a_killed_export_left(trained, tmp_path):
    subject, _ = trained
    out = tmp_path / "clip"
    argv = [str(subject), "--out", str(out), "--quiet"]
    export = subprocess.Popen(
        [sys.executable, "-c", SLOW_EXPORT, *argv], cwd=REPO, env=cli_env(), stderr=subprocess.PIPE, text=True
    )
    wait_for(lambda: any(tmp_path.glob(".clip.*.partial")) or export.poll() is not None, timeout_s=300)
    export.send_signal(signal.SIGTERM)
    _, err = export.communicate(timeout=120)
    assert export.returncode == 143, err
    assert err.splitlines() == [f"interactavatar-export: terminated; nothing written to {out}"]
    assert list(tmp_path.iterdir()) == []
    stale = tmp_path / ".clip.0123456789ab.partial"  # left by an export that was killed (no process holds it)
    stale.mkdir()
    (stale / "00000.ply").write_bytes(b"")
    live = tmp_path / ".clip.fedcba987654.partial"  # an export writing now: it holds its folder's lock
    live.mkdir()
    held = os.open(live, os.O_RDONLY)
    try:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert main([str(subject), "--frames", "0", "--out", str(out), "--quiet"]) == 0
    finally:
        os.close(held)
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name, "clip"]


CTRL_C_ON_IMPORT = """\
import importlib.abc, os, signal, sys
class CtrlC(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == sys.argv[1]:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, CtrlC())
from pipeline.export_ply import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("importing", ["torch", "avatar.representations"])
def test_ctrl_c_while_the_command_starts_is_one_line_and_exit_130(trained, tmp_path, importing: str) -> None:
    """Ctrl-C while torch or the core is being imported (the signal sent from the import of ``importing``, so the
    moment does not depend on the machine's speed): one line, exit 130, nothing written."""
    subject, _ = trained
    out = tmp_path / "clip"
    export = subprocess.run(
        [sys.executable, "-c", CTRL_C_ON_IMPORT, importing, str(subject), "--out", str(out)],
        cwd=REPO,
        env=cli_env(),
        capture_output=True,
        text=True,
        preexec_fn=default_sigint,
        timeout=120,
    )
    assert export.returncode == 130, export.stderr
    assert export.stderr.splitlines() == [f"interactavatar-export: interrupted; nothing written to {out}"]
    assert list(tmp_path.iterdir()) == []
