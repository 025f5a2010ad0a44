"""What the viewer's browser tests share: the skip conditions, one headless Chromium per module, the page opened at
scale 1 (canvas pixels = camera pixels; each module gives its ``viewer_dir``), and the check of pose.js against the
codec."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from avatar.viewer.page import BUNDLE
from benchmarks.viewer_browser import CHROMIUM, INSTALL_HINT, ViewerPage, chromium, decoded_frame, open_viewer

#: the browser tests' marks: skipped, saying how to get them, without chromium or the page's bundle
NEEDS_BROWSER = [
    pytest.mark.skipif(CHROMIUM is None, reason=INSTALL_HINT),
    pytest.mark.skipif(not BUNDLE.is_file(), reason=f"the viewer page is not built: make viewer ({BUNDLE})"),
]


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with chromium() as running:
        yield running


@pytest.fixture(scope="module")
def page(browser: object, viewer_dir: Path) -> Iterator[ViewerPage]:
    """The module's page, opened from the file system at scale 1."""
    with open_viewer(browser, f"{(viewer_dir / 'index.html').as_uri()}?scale=1") as viewer:
        yield viewer


def assert_posed_as_decoded(page: ViewerPage, viewer_dir: Path, motion: str, frame: int, camera: str) -> None:
    """pose.js against avatar/viewer/codec.py's decode_frame, the reference it follows, on a frame with overrides of
    both kinds: the same Gaussians."""
    page.show(motion, frame, camera)
    shown = page.posed()
    reference, overrides = decoded_frame(viewer_dir, motion, frame)
    assert overrides.geometry.size > 0 and overrides.appearance.size > 0
    np.testing.assert_allclose(shown["centers"], reference.means, atol=1e-9)
    np.testing.assert_allclose(shown["scales"], reference.scales, rtol=1e-9)
    np.testing.assert_allclose(np.abs((shown["quats"] * reference.quats).sum(1)), 1, atol=1e-9)
    np.testing.assert_allclose(shown["rgba"][:, :3], reference.colors, atol=1e-9)
    np.testing.assert_allclose(shown["rgba"][:, 3], reference.opacities, atol=1e-9)
