"""Settings that used to pass the dry run and fail at their stage (after training, for the reenactment's) are
refused before any stage runs, one line each naming the key and the fix (issue 52, items 6 to 8)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from data_schemas.deform import DEFORM
from data_schemas.params import PARAMS
from data_schemas.tables import write_table
from pipeline.config import CONF_DIR, ConfigError, validate_config
from stages import REGISTRY
from tests.conftest import TOY_OVERRIDES, cli_command, cli_env, compose_cfg

#: (overrides, the one line that refuses them)
BAD = [
    (
        ["dataset.appearance=nosuch"],
        "dataset.appearance=nosuch: not in the synthetic dataset; choose one of full,",
    ),
    (["dataset.scene=nosuch"], "dataset.scene=nosuch: not in the synthetic dataset; choose one of interaction,"),
    (["subject=synth_z"], "subject=synth_z: not in the synthetic dataset; choose one of synth_a, synth_b, synth_c"),
    (["reenact.placement=nosuch"], "reenact.placement=nosuch: choose one of contact, scaled"),
    (["stage.reenact.cameras=[cam00,cam08]"], "stage.reenact.cameras=['cam00', 'cam08']: ['cam08'] not among"),
    (["stage.compare.methods=[interactavatar,nosuch]"], "['nosuch'] are not methods; choose among ['gaussian_avatars'"),
    (["stage.viewer.motions=[train,train]"], "stage.viewer.motions=['train', 'train']: choose one or more of"),
    (["stage.viewer.motions=[train,nosuch]"], "stage.viewer.motions=['train', 'nosuch']: choose one or more of"),
    (["stage.viewer.fps=0"], "stage.viewer.fps=0.0: must be > 0"),
    (["stage.viewer.jpeg_quality=101"], "stage.viewer.jpeg_quality=101: must be between 1 and 100"),
    (["stage.viewer.jpeg_quality=0"], "stage.viewer.jpeg_quality=0: must be between 1 and 100"),
    (["dataset=folder"], "dataset.root: not set; dataset=folder reads <root>/<subject>/...; set dataset.root=/path"),
    (["paths.outputs="], "paths.outputs is empty; set it to a folder, e.g. paths.outputs=outputs"),
]


def _problems(overrides: list[str]) -> tuple[str, ...]:
    """The problems ``validate_config`` finds in the app's config with ``overrides`` (none: ``()``)."""
    try:
        validate_config(compose_cfg(overrides), REGISTRY)
    except ConfigError as exc:
        return exc.problems
    return ()


def _refused_once(overrides: list[str], message: str) -> None:
    problems = _problems(overrides)
    assert sum(message in p for p in problems) == 1, problems


@pytest.mark.parametrize(("overrides", "message"), BAD)
def test_a_setting_its_stage_would_refuse_is_refused_before_any_stage(
    tmp_path: Path, overrides: list[str], message: str
) -> None:
    _refused_once([f"paths.outputs={tmp_path / 'out'}", *overrides], message)


def test_the_good_neighbours_of_the_refused_values_pass(tmp_path: Path) -> None:
    for overrides in (
        ["stage.reenact.cameras=[cam07]"],
        ["stage.capture.num_cameras=9", "stage.reenact.cameras=[cam08]"],
        ["stage.compare.methods=[interactavatar,no_pbd]"],
        ["stage.viewer.motions=[test,train]", "stage.viewer.fps=0.5", "stage.viewer.jpeg_quality=100"],
        ["reenact.placement=scaled"],
        ["method=splatting_avatar", "splatting.scene_extent=0"],  # 0: the meshes' bounding radius
    ):
        assert _problems([f"paths.outputs={tmp_path / 'out'}", *overrides]) == (), overrides


def test_outputs_where_no_folder_can_be_made_is_one_line() -> None:
    """/proc passes a permission check (as root) but no folder can be made in it: Hydra's traceback before."""
    if not Path("/proc").is_dir():
        pytest.skip("no /proc here")
    _refused_once(["paths.outputs=/proc/x"], "paths.outputs=/proc/x: no folder can be made in /proc")


def test_an_empty_outputs_writes_nothing_in_the_current_folder(tmp_path: Path) -> None:
    """``paths.outputs=`` used to mean the current folder: a dry run wrote ``_hydra/`` and ``<subject>/`` there."""
    done = subprocess.run(
        cli_command(*TOY_OVERRIDES, "paths.outputs=", "run.dry=true"),
        cwd=tmp_path,
        env=cli_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "paths.outputs is empty" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert list(tmp_path.iterdir()) == []


def _params_table(path: Path) -> Path:
    sizes = {c.name: c.size or 10 for c in PARAMS.columns if c.name != "frame"}
    write_table(path, PARAMS, {"frame": np.arange(2), **{k: np.zeros((2, n), np.float32) for k, n in sizes.items()}})
    return path


def test_the_driver_file_is_read_before_any_stage(tmp_path: Path) -> None:
    """A driver file that is not a params table was found by the reenact stage, after training."""
    text = tmp_path / "driver.csv"
    text.write_text("frame,flame_shape\n0,0\n")
    garbage = tmp_path / "garbage.parquet"
    garbage.write_text("not parquet")
    deform = tmp_path / "deform.parquet"
    write_table(deform, DEFORM, {"frame": np.arange(2), "contact": np.zeros(2, bool), "offsets": np.zeros((2, 3))})
    out = f"paths.outputs={tmp_path / 'out'}"
    for driver, message in (
        (text, f"reenact.driver={text}: not a .parquet file"),
        (garbage, f"reenact.driver={garbage}: not a params table ({garbage}: not a readable Parquet file"),
        (deform, f"reenact.driver={deform}: not a params table ({deform}: expected a 'params' table"),
        ("x.npz", "reenact.driver=x.npz: no such file"),  # was taken for a subject's name
    ):
        _refused_once([out, f"reenact.driver={driver}"], message)
    assert _problems([out, f"reenact.driver={_params_table(tmp_path / 'params.parquet')}"]) == ()


def test_reenact_cameras_of_a_capture_folder_are_read_from_its_listing(tmp_path: Path) -> None:
    for sequence, cameras in (("train", ("left", "right")), ("test", ("left", "right"))):
        videos = tmp_path / "root" / "mine" / sequence / "videos"
        videos.mkdir(parents=True)
        for camera in cameras:
            (videos / f"{camera}.mp4").write_bytes(b"")
    folder = [
        f"paths.outputs={tmp_path / 'out'}",
        "dataset=folder",
        f"dataset.root={tmp_path / 'root'}",
        "subject=mine",
    ]
    _refused_once(
        [*folder, "stage.reenact.cameras=[middle]"], "['middle'] not among the capture's cameras ['left', 'right']"
    )
    assert _problems([*folder, "stage.reenact.cameras=[right]"]) == ()
    assert _problems([*folder, "subject=other", "stage.reenact.cameras=[middle]"]) == (  # no folder: that alone
        f"{tmp_path / 'root' / 'other'}: capture folder missing; set dataset.root so that <root>/other exists",
    )


def test_no_setting_documents_a_meaning_for_negative_values() -> None:
    """Every negative number is refused before any stage runs (``pipeline.config.numeric_problems``), so no comment
    of the config may give one a meaning (``splatting.scene_extent`` said ``<= 0: the meshes' bounding radius``)."""
    negative = re.compile(r"<=? *0\b|negative")
    claims = [
        f"{path.relative_to(CONF_DIR)}:{number}: {line.strip()}"
        for path in sorted(CONF_DIR.rglob("*.yaml"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if "#" in line and negative.search(line.split("#", 1)[1])
    ]
    assert not claims, claims


def test_a_method_on_the_search_path_may_be_compared(tmp_path: Path) -> None:
    """A method defined by one YAML file of the user's (``hydra.searchpath``) is a method to the comparison's check;
    a name no file defines is still refused."""
    from tests.conftest import run_cli
    from tests.test_end_to_end import EIGHTH_METHOD

    (tmp_path / "conf" / "method").mkdir(parents=True)
    (tmp_path / "conf" / "method" / "eighth.yaml").write_text(EIGHTH_METHOD)
    common = [f"paths.outputs={tmp_path / 'out'}", "run.dry=true", f"hydra.searchpath=[file://{tmp_path / 'conf'}]"]
    listed = run_cli(*common, "stage.compare.methods=[interactavatar,eighth]")
    assert listed.returncode == 0, listed.stderr
    unknown = run_cli(*common, "stage.compare.methods=[interactavatar,ninth]")
    assert unknown.returncode == 2 and "['ninth'] are not methods" in unknown.stderr, unknown.stderr


def test_a_batch_may_compare_a_method_on_the_search_path(tmp_path: Path) -> None:
    """The batch's own check of every job (before any is started) knows the user's methods too."""
    from tests.conftest import run_cli
    from tests.test_end_to_end import EIGHTH_METHOD

    (tmp_path / "conf" / "method").mkdir(parents=True)
    (tmp_path / "conf" / "method" / "eighth.yaml").write_text(EIGHTH_METHOD)
    batch = run_cli(
        "-m",
        f"paths.outputs={tmp_path / 'out'}",
        "run.dry=true",
        f"hydra.searchpath=[file://{tmp_path / 'conf'}]",
        "stage.compare.methods=[interactavatar,eighth]",
        "method=interactavatar,eighth",
    )
    assert batch.returncode == 0, batch.stderr
