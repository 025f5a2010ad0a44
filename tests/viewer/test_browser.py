"""The browser viewer in a real browser: headless Debian Chromium, WebGL in SwiftShader, on the smoke run's outputs.

Needs ``chromium`` (``make browser`` installs it as root; ``apt-get install chromium``) and the page's bundle
(``make viewer``); without them the tests are skipped with that instruction. The smoke DAG up to the viewer runs once
for the module (about 1.5 minutes on 2 cores); the browser tests themselves take about 30 s.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from avatar.metrics import image_metrics
from avatar.viewer_codec import (
    Overrides,
    Ranges,
    StaticGaussians,
    decode_frame,
    mask_indices,
    sums_in_time,
    unpack_sections,
)
from benchmarks.viewer_browser import (
    CHROMIUM,
    INSTALL_HINT,
    ProjectRender,
    ViewerPage,
    chromium,
    manifest,
    open_viewer,
    psnr,
)
from stages.viewer import BUNDLE
from tests.conftest import REPO, run_cli

pytestmark = [
    pytest.mark.skipif(CHROMIUM is None, reason=INSTALL_HINT),
    pytest.mark.skipif(not BUNDLE.is_file(), reason=f"the viewer page is not built: make viewer ({BUNDLE})"),
]
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
def browser() -> Iterator[object]:
    with chromium() as running:
        yield running


@pytest.fixture(scope="module")
def page(browser: object, viewer_dir: Path) -> Iterator[ViewerPage]:
    """The smoke avatar's page, opened from the file system at scale 1 (canvas pixels = camera pixels)."""
    with open_viewer(browser, f"{(viewer_dir / 'index.html').as_uri()}?scale=1") as viewer:
        yield viewer


@pytest.fixture(scope="module")
def project(smoke: Path) -> ProjectRender:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=["quality=smoke", f"method={METHOD}"])
    return ProjectRender(smoke, cfg, METHOD)


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
    """pose.js against avatar/viewer_codec.py's decode_frame, the reference it follows: the same Gaussians."""
    page.show("train", 3, manifest(viewer_dir)["motions"][0]["cameras"][0]["id"])
    shown = page.posed()
    data = _load(viewer_dir / "data" / "avatar.js")
    motion = _load(viewer_dir / "data" / "motion-train.js")
    entry = manifest(viewer_dir)["motions"][0]
    ranges = Ranges(np.asarray(entry["ranges"]["vertex_lo"]), np.asarray(entry["ranges"]["vertex_hi"]))
    static = StaticGaussians(*(data[k] for k in StaticGaussians.__dataclass_fields__))
    N = static.triangle.shape[0]
    spans = {}
    for kind in ("geometry", "appearance"):
        index = mask_indices(motion[f"{kind}_mask"][3], N)
        start = int(motion[f"{kind}_start"][3])
        spans[kind] = (index, slice(start, start + len(index)))
    (g, gs), (a, as_) = spans["geometry"], spans["appearance"]
    overrides = Overrides(
        g, motion["d_mean"][gs], motion["d_log_scale"][gs], motion["d_rotation"][gs], a, motion["d_rgba"][as_]
    )
    vertices = sums_in_time(motion["vertices"])[3]
    reference = decode_frame(static, vertices, overrides, ranges, data["faces"].astype(np.int64))
    assert len(g) > 0 and len(a) > 0  # H changes the hand: the frame has overrides of both kinds
    np.testing.assert_allclose(shown["centers"], reference.means, atol=1e-9)
    np.testing.assert_allclose(shown["scales"], reference.scales, rtol=1e-9)
    np.testing.assert_allclose(np.abs((shown["quats"] * reference.quats).sum(1)), 1, atol=1e-9)
    np.testing.assert_allclose(shown["rgba"][:, :3], reference.colors, atol=1e-9)
    np.testing.assert_allclose(shown["rgba"][:, 3], reference.opacities, atol=1e-9)


def _load(path: Path) -> dict[str, np.ndarray]:
    import base64
    import json
    import re

    match = re.search(r'= \{sections: (.*), data: "(.*)"\};', path.read_text())
    assert match is not None, path
    return unpack_sections(base64.b64decode(match.group(2)), json.loads(match.group(1)))


def test_the_timeline_the_motion_selector_and_the_toggles_change_what_is_drawn(
    page: ViewerPage, viewer_dir: Path
) -> None:
    camera = manifest(viewer_dir)["motions"][0]["cameras"][0]["id"]
    page.show("train", 0, camera)
    first = page.canvas()
    # the timeline: dragged to frame 4
    page.page.eval_on_selector("#timeline", "e => { e.value = 4; e.dispatchEvent(new Event('input')); }")
    page.settle()
    assert page.state()["frame"] == 4
    assert psnr(page.canvas(), first) < 35
    assert "frame 5 / " in page.page.inner_text("#frame-label")
    # frame stepping
    page.page.click("#prev")
    page.settle()
    assert page.state()["frame"] == 3
    # the motion selector
    before = page.canvas()
    page.page.select_option("#motion", "test")
    page.page.wait_for_function("window.viewer.state.motion === 'test'")
    page.settle()
    assert page.state()["frame"] == 0 and psnr(page.canvas(), before) < 35
    # the toggles: without the hand, then without the face, less is drawn, and both back restore the image
    page.page.select_option("#motion", "train")
    page.page.wait_for_function("window.viewer.state.motion === 'train'")
    page.show("train", 0, camera)
    whole = page.canvas()
    background = np.asarray(manifest(viewer_dir)["background"], dtype=np.float32)
    drawn = np.abs(whole - background).max(-1) > 0.1
    for box in ("#show-hand", "#show-face"):
        page.page.uncheck(box)
        page.settle()
        without = np.abs(page.canvas() - background).max(-1) > 0.1
        assert without.sum() < 0.9 * drawn.sum(), box
        page.page.check(box)
        page.settle()
    assert psnr(page.canvas(), whole) > 40


def test_contact_frames_are_marked_on_the_timeline(page: ViewerPage, viewer_dir: Path) -> None:
    page.page.select_option("#motion", "train")
    page.page.wait_for_function("window.viewer.state.motion === 'train'")
    page.settle()
    contact = next(m for m in manifest(viewer_dir)["motions"] if m["name"] == "train")["contact"]
    assert page.page.locator(".contact-mark").count() == sum(contact) > 0


def test_frame_time_in_swiftshader_is_reported(page: ViewerPage) -> None:
    stats = page.frame_ms(2.0)
    print(f"SwiftShader, smoke avatar: frame {stats['frame_ms']:.1f} ms, posing {stats['pose_ms']:.1f} ms")
    assert stats["frame_ms"] > 0 and stats["pose_ms"] > 0
    assert "frame" in page.page.inner_text("#stats")


def test_interactavatar_view_serves_the_page(browser: object, smoke: Path) -> None:
    server = subprocess.Popen(
        [str(Path(sys.executable).with_name("interactavatar-view")), str(smoke)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None
        url = server.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:") and url.endswith(f"/methods/{METHOD}/viewer/index.html")
        with open_viewer(browser, url) as viewer:
            assert viewer.errors == []
            assert viewer.page.evaluate("document.body.dataset.ready") == "true"
    finally:
        server.terminate()
        server.wait(timeout=10)


def test_a_page_without_its_bundle_says_how_to_build_it(browser: object, viewer_dir: Path, tmp_path: Path) -> None:
    copy = tmp_path / "viewer"
    shutil.copytree(viewer_dir, copy)
    (copy / "viewer.js").unlink()
    with open_viewer(browser, (copy / "index.html").as_uri()) as viewer:
        assert "make viewer" in viewer.page.inner_text("#message")


def test_interactavatar_view_refuses_a_folder_without_a_viewer(tmp_path: Path) -> None:
    run = subprocess.run(
        [str(Path(sys.executable).with_name("interactavatar-view")), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert run.returncode == 2 and "run.only=viewer" in run.stderr
