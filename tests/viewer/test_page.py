"""The browser viewer's page in a real browser (headless Debian Chromium, WebGL in SwiftShader), on a toy avatar the
stage's own writer puts in a folder in a second (tests/viewer/toy_viewer.py): part of the default suite (about 40 s).
The same checks on the smoke run's real avatar are in test_smoke_viewer.py (slow: it needs the DAG).

Needs ``chromium`` (``make browser`` installs it as root; ``apt-get install chromium``) and the page's bundle
(``make viewer``); without them the tests are skipped with that instruction.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar.metrics import image_metrics
from avatar.posing import MeshSequence
from benchmarks.viewer_browser import (
    ViewerPage,
    manifest,
    open_viewer,
    psnr,
)
from tests.viewer.conftest import NEEDS_BROWSER, assert_posed_as_decoded
from tests.viewer.toy_viewer import BACKGROUND, ToyAvatar, render, write_toy_viewer

pytestmark = [*NEEDS_BROWSER]


@pytest.fixture(scope="module")
def toy(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ToyAvatar, dict[str, MeshSequence]]:
    """A subject folder holding the toy's viewer (methods/toy/viewer), the avatar and its motions' meshes."""
    subject = tmp_path_factory.mktemp("toy_subject")
    avatar, sequences = write_toy_viewer(subject / "methods" / "toy" / "viewer")
    return subject, avatar, sequences


@pytest.fixture(scope="module")
def viewer_dir(toy: tuple[Path, ToyAvatar, dict[str, MeshSequence]]) -> Path:
    return toy[0] / "methods" / "toy" / "viewer"


def _drawn(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels away from the background."""
    return np.abs(image - np.asarray(BACKGROUND, dtype=np.float32)).max(-1) > 0.1


def test_the_page_opens_from_the_file_system_without_errors_draws_and_shows_the_ground_truth(
    page: ViewerPage,
) -> None:
    assert page.errors == []
    page.show("train", 0, "front")
    assert 0.1 < _drawn(page.canvas()).mean() < 0.9
    assert page.page.is_visible("#gt") and page.page.get_attribute("#gt", "src").endswith("train/front/00000.jpg")
    page.show("test", 0, "front")  # the held-out motion of the toy has no ground truth
    assert not page.page.is_visible("#gt")


@pytest.mark.parametrize(("frame", "camera"), [(2, "front"), (5, "side")])
def test_a_frame_matches_the_projects_own_render_of_it(
    page: ViewerPage, toy: tuple[Path, ToyAvatar, dict[str, MeshSequence]], frame: int, camera: str
) -> None:
    """Frame k at a capture camera against the project's rasterizer: PSNR >= 28 dB, SSIM >= 0.95, and closer to the
    render of k than to those of k-2 and k+2 (the frame shown is the one asked for)."""
    _, avatar, sequences = toy
    page.show("train", frame, camera)
    shown, ours = page.canvas(), render(avatar, sequences["train"], frame, camera)
    metrics = image_metrics(torch.from_numpy(shown).permute(2, 0, 1), torch.from_numpy(ours).permute(2, 0, 1), None)
    print(f"toy frame {frame}, camera {camera}: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}")
    assert metrics["psnr"] >= 28 and metrics["ssim"] >= 0.95
    for other in (frame - 2, frame + 2):
        assert psnr(shown, ours) > psnr(shown, render(avatar, sequences["train"], other, camera)) + 3


def test_the_pages_posing_is_the_codecs_decoding(page: ViewerPage, viewer_dir: Path) -> None:
    """pose.js against avatar/viewer/codec.py's decode_frame, the reference it follows, on a frame with overrides of
    both kinds: the same Gaussians."""
    assert_posed_as_decoded(page, viewer_dir, "train", 5, "front")


def test_the_timeline_the_motion_selector_and_the_toggles_change_what_is_drawn(page: ViewerPage) -> None:
    page.show("train", 0, "front")
    first = page.canvas()
    page.page.eval_on_selector("#timeline", "e => { e.value = 6; e.dispatchEvent(new Event('input')); }")
    page.settle()
    assert page.state()["frame"] == 6 and "frame 7 / 8" in page.page.inner_text("#frame-label")
    assert psnr(page.canvas(), first) < 35
    page.page.click("#prev")
    page.settle()
    assert page.state()["frame"] == 5
    before = page.canvas()
    page.page.select_option("#motion", "test")  # the toy's held-out motion is its train motion played backwards
    page.page.wait_for_function("window.viewer.state.motion === 'test'")
    page.settle()
    assert page.state()["frame"] == 0 and psnr(page.canvas(), before) < 35
    page.show("train", 0, "front")
    whole = page.canvas()
    for box in ("#show-hand", "#show-face"):
        page.page.uncheck(box)
        page.settle()
        without = page.canvas()
        assert psnr(without, whole) < 30, box
        if box == "#show-face":  # the hand, in front of the face, covers it: only the face leaves the background
            assert _drawn(without).sum() < 0.5 * _drawn(whole).sum()
        page.page.check(box)
        page.settle()
    assert psnr(page.canvas(), whole) > 40
    page.page.select_option("#camera", "side")
    page.settle()
    assert page.state()["camera"] == "side" and psnr(page.canvas(), whole) < 35


def test_contact_frames_are_marked_on_the_timeline(page: ViewerPage, viewer_dir: Path) -> None:
    page.show("train", 0, "front")
    contact = next(m for m in manifest(viewer_dir)["motions"] if m["name"] == "train")["contact"]
    assert page.page.locator(".contact-mark").count() == sum(contact) == 3


def test_an_idle_page_draws_nothing_and_a_change_draws_again(page: ViewerPage) -> None:
    page.show("train", 1, "front")
    page.page.wait_for_timeout(300)  # a draw Spark asks for after its last sort may still come
    idle = page.page.evaluate("window.viewer.draws()")
    page.page.wait_for_timeout(700)
    assert page.page.evaluate("window.viewer.draws()") == idle
    page.page.click("#next")
    page.page.wait_for_timeout(300)
    assert page.page.evaluate("window.viewer.draws()") > idle


def test_playing_reports_the_frame_time(page: ViewerPage) -> None:
    stats = page.frame_ms(1.5)
    print(f"SwiftShader, toy avatar: frame {stats['frame_ms']:.1f} ms, posing {stats['pose_ms']:.2f} ms")
    assert stats["frame_ms"] > 0 and stats["pose_ms"] > 0 and "frame" in page.page.inner_text("#stats")


def test_interactavatar_view_serves_the_page(
    browser: object, toy: tuple[Path, ToyAvatar, dict[str, MeshSequence]]
) -> None:
    server = subprocess.Popen(
        [str(Path(sys.executable).with_name("interactavatar-view")), str(toy[0])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None
        url = server.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:") and url.endswith("/methods/toy/viewer/index.html")
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
