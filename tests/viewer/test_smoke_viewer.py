"""The browser viewer of the smoke run's real avatar (trained H and I, the capture's cameras) in headless Debian
Chromium, WebGL in SwiftShader: the page's frames against the project's renders at the capture cameras, pose.js
against the codec, every motion played. Slow: the smoke DAG up to the viewer runs first (about 40 s on 2 cores) and
the checks take about a minute; the page's controls are tested on a toy avatar in the default suite (test_page.py).

Needs ``chromium`` (``make browser`` installs it as root; ``apt-get install chromium``) and the page's bundle
(``make viewer``); without them the tests are skipped with that instruction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from avatar.metrics import image_metrics
from benchmarks.viewer_browser import (
    ProjectRender,
    ViewerPage,
    manifest,
    psnr,
)
from tests.conftest import REPO, run_cli
from tests.viewer.conftest import NEEDS_BROWSER, assert_posed_as_decoded

pytestmark = [pytest.mark.slow, *NEEDS_BROWSER]
METHOD = "interactavatar"


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The smoke run's subject folder, its DAG run up to the viewer."""
    out = tmp_path_factory.mktemp("viewer") / "out"
    run = run_cli(f"paths.outputs={out}", "quality=smoke", "run.progress=false", "run.until=viewer")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return out / "synth_a"


@pytest.fixture(scope="module")
def viewer_dir(smoke: Path) -> Path:
    return smoke / "methods" / METHOD / "viewer"


@pytest.fixture(scope="module")
def project(smoke: Path) -> ProjectRender:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=["quality=smoke", f"method={METHOD}"])
    return ProjectRender(smoke, cfg, METHOD, backend="auto")


def test_the_page_opens_from_the_file_system_without_errors_and_draws(page: ViewerPage, viewer_dir: Path) -> None:
    assert page.errors == []
    assert page.page.evaluate("document.body.dataset.ready") == "true"
    image = page.canvas()
    background = np.asarray(manifest(viewer_dir)["background"], dtype=np.float32)
    drawn = np.abs(image - background).max(-1) > 0.1
    assert 0.05 < drawn.mean() < 0.95, f"{drawn.mean():.1%} of the canvas differs from the background"


@pytest.mark.parametrize(("motion", "frame", "camera_index"), [("train", 2, 0), ("test", 1, -1)])
def test_a_frame_matches_the_projects_own_render_of_it(
    page: ViewerPage, project: ProjectRender, viewer_dir: Path, motion: str, frame: int, camera_index: int
) -> None:
    """At a capture camera, the browser's frame k against the rasterizer's: PSNR >= 28 dB, SSIM >= 0.95; and it is
    frame k, closer to the render of k than to those of k-2 and k+2."""
    entry = next(m for m in manifest(viewer_dir)["motions"] if m["name"] == motion)
    camera = entry["cameras"][camera_index]["id"]
    page.show(motion, frame, camera)
    shown = page.canvas()
    ours = project.render(motion, frame, camera)
    assert shown.shape == ours.shape
    metrics = image_metrics(torch.from_numpy(shown).permute(2, 0, 1), torch.from_numpy(ours).permute(2, 0, 1), None)
    print(f"{motion} frame {frame} camera {camera}: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}")
    assert metrics["psnr"] >= 28 and metrics["ssim"] >= 0.95
    for other in (frame - 2, frame + 2):
        if 0 <= other < entry["frames"]:
            assert psnr(shown, ours) > psnr(shown, project.render(motion, other, camera)) + 3


def test_the_pages_posing_is_the_codecs_decoding(page: ViewerPage, viewer_dir: Path) -> None:
    """pose.js against avatar/viewer/codec.py's decode_frame on the real avatar, whose H changes the hand."""
    assert_posed_as_decoded(page, viewer_dir, "train", 3, manifest(viewer_dir)["motions"][0]["cameras"][0]["id"])


def test_every_motion_plays_without_errors_and_reports_its_frame_time(page: ViewerPage, viewer_dir: Path) -> None:
    for motion in manifest(viewer_dir)["motions"]:
        page.page.select_option("#motion", motion["name"])
        page.page.wait_for_function(f"window.viewer.state.motion === '{motion['name']}'")
        stats = page.frame_ms(1.5)
        name, frame_ms, pose_ms = motion["name"], stats["frame_ms"], stats["pose_ms"]
        print(f"SwiftShader, smoke avatar, {name}: frame {frame_ms:.1f} ms, posing {pose_ms:.1f} ms")
        assert stats["frame_ms"] > 0
    assert page.errors == []
