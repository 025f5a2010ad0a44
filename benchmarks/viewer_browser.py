"""The browser viewer (stage ``viewer``) driven in headless Chromium, and the project's own render of the same frame
at the same camera: what the viewer's tests and ``bench_viewer.py`` compare.

Chromium is Debian's (``apt-get install chromium``; ``make browser`` installs it as root), driven by Playwright
(``playwright`` from PyPI, its browser download never used: ``executable_path`` names the system's). WebGL runs in
SwiftShader, a software renderer, so frame times here are a floor, not a GPU's.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import HELD_OUT_SEQUENCE, TRAIN_SEQUENCE, method_params
from avatar.artifacts.motion import applied_deformation, posed_sequence
from avatar.render.gaussians import render_gaussians
from avatar.representations import load_trained
from avatar.viewer.codec import (
    FrameGaussians,
    Overrides,
    Ranges,
    StaticGaussians,
    decode_frame,
    mask_indices,
    sums_in_time,
    unpack_sections,
)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
INSTALL_HINT = "needs Debian's chromium (apt-get install chromium, or make browser as root) and playwright"
#: WebGL through SwiftShader in a headless Chromium on a machine without a GPU and without network access.
CHROMIUM_ARGS = (
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


@dataclass
class ViewerPage:
    """An open viewer page (Playwright's ``page``) and what its console reported (``errors``: console errors and
    uncaught exceptions)."""

    page: Any
    errors: list[str] = field(default_factory=list)

    def show(self, motion: str, frame: int, camera: str) -> None:
        """Draw ``frame`` of ``motion`` from capture camera ``camera``; returns once it is sorted and drawn."""
        self.page.evaluate(f"window.viewer.show({json.dumps({'motion': motion, 'frame': frame, 'camera': camera})})")

    def canvas(self) -> np.ndarray:
        """The render canvas' pixels (H, W, 3) float32 in [0, 1]."""
        url = self.page.evaluate("document.getElementById('render').toDataURL('image/png')")
        png = np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8)
        return cv2.imdecode(png, cv2.IMREAD_COLOR)[:, :, ::-1].astype(np.float32) / 255

    def settle(self) -> None:
        self.page.evaluate("window.viewer.settle()")

    def state(self) -> dict:
        return self.page.evaluate("({...window.viewer.state})")

    def posed(self) -> dict[str, np.ndarray]:
        """The page's Gaussians of the frame shown: centers (N, 3), scales (N, 3), quats (N, 4), rgba (N, 4)."""
        arrays = self.page.evaluate("window.viewer.posed()")
        width = {"centers": 3, "scales": 3, "quats": 4, "rgba": 4}
        return {k: np.asarray(v, dtype=np.float64).reshape(-1, width[k]) for k, v in arrays.items()}

    def frame_ms(self, seconds: float = 3.0) -> dict[str, float]:
        """Play for ``seconds`` and return the page's median times: ``frame_ms`` (between drawn frames while
        playing) and ``pose_ms`` (posing the Gaussians of a frame and handing them to Spark)."""
        self.page.click("#play")
        self.page.wait_for_timeout(seconds * 1000)
        self.page.click("#play")
        return self.page.evaluate("({...window.viewer.stats})")


@contextmanager
def chromium() -> Iterator[Any]:
    """Headless Chromium (Playwright's ``Browser``), closed on exit; one per process at a time."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS))
        try:
            yield browser
        finally:
            browser.close()


@contextmanager
def open_viewer(browser: Any, url: str, width: int = 1200, height: int = 800) -> Iterator[ViewerPage]:
    """Open the viewer at ``url`` (``file://`` or ``http://``) in a new page of ``browser``; yields once it is ready
    (or has failed: see ``errors`` and the page's message)."""
    page = browser.new_page(viewport={"width": width, "height": height})
    try:
        viewer = ViewerPage(page)
        page.on("console", lambda m: viewer.errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: viewer.errors.append(str(e)))
        page.goto(url)
        page.wait_for_function("document.body.dataset.ready === 'true' || window.viewerFailed", timeout=60_000)
        yield viewer
    finally:
        page.close()


def manifest(viewer_dir: Path) -> dict:
    """The page's manifest (``data/manifest.js``)."""
    text = (viewer_dir / "data" / "manifest.js").read_text()
    match = re.search(r"window\.IAV\.manifest = (.*);", text)
    if match is None:
        raise ValueError(f"{viewer_dir / 'data' / 'manifest.js'}: no manifest")
    return json.loads(match.group(1))


def read_data(path: Path) -> dict[str, np.ndarray]:
    """The arrays of one of the page's data scripts (``data/avatar.js``, ``data/motion-<name>.js``)."""
    match = re.search(r'= \{sections: (.*), data: "(.*)"\};', path.read_text())
    if match is None:
        raise ValueError(f"{path}: not a viewer data script")
    return unpack_sections(base64.b64decode(match.group(2)), json.loads(match.group(1)))


def decoded_frame(viewer_dir: Path, motion: str, frame: int) -> tuple[FrameGaussians, Overrides]:
    """Frame ``frame`` of ``motion`` as :func:`avatar.viewer.codec.decode_frame` decodes it from the page's files
    (the reference of the page's pose.js), and the frame's overrides."""
    data = read_data(viewer_dir / "data" / "avatar.js")
    arrays = read_data(viewer_dir / "data" / f"motion-{motion}.js")
    entry = next(m for m in manifest(viewer_dir)["motions"] if m["name"] == motion)
    ranges = Ranges(np.asarray(entry["ranges"]["vertex_lo"]), np.asarray(entry["ranges"]["vertex_hi"]))
    static = StaticGaussians(*(data[k] for k in StaticGaussians.__dataclass_fields__))
    count = static.triangle.shape[0]
    spans = {}
    for kind in ("geometry", "appearance"):
        index = mask_indices(arrays[f"{kind}_mask"][frame], count)
        start = int(arrays[f"{kind}_start"][frame])
        spans[kind] = (index, slice(start, start + len(index)))
    (g, gs), (a, as_) = spans["geometry"], spans["appearance"]
    overrides = Overrides(
        g, arrays["d_mean"][gs], arrays["d_log_scale"][gs], arrays["d_rotation"][gs], a, arrays["d_rgba"][as_]
    )
    vertices = sums_in_time(arrays["vertices"])[frame]
    return decode_frame(static, vertices, overrides, ranges, data["faces"].astype(np.int64)), overrides


class ProjectRender:
    """The project's own render (the rasterizer stage evaluate uses) of a motion's frames at the viewer's capture
    cameras: ``render(motion, frame, camera)`` (H, W, 3) float32, for the train and held-out motions."""

    def __init__(self, subject_dir: Path, cfg: DictConfig, method: str, backend: str = "torch") -> None:
        self.subject_dir, self.cfg, self.backend = subject_dir, cfg, backend
        self.dynamic = subject_dir / "methods" / method / "dynamic"
        self.model = load_trained(self.dynamic)
        self.manifest = manifest(subject_dir / "methods" / method / "viewer")
        self._posed: dict[str, Any] = {}

    def _sequence(self, motion: str) -> Any:
        if motion not in self._posed:
            sequence = TRAIN_SEQUENCE if motion == "train" else HELD_OUT_SEQUENCE
            fit, pbd = self.subject_dir / "fit", self.subject_dir / "pbd"
            posed = posed_sequence(
                fit, sequence, self.cfg, applied_deformation(self.cfg, pbd), method_params(self.dynamic, fit, sequence)
            )
            self._posed[motion] = (posed, posed.conditioning(self.cfg))
        return self._posed[motion]

    def render(self, motion: str, frame: int, camera: str) -> np.ndarray:
        posed, cond = self._sequence(motion)
        view = next(
            c for m in self.manifest["motions"] if m["name"] == motion for c in m["cameras"] if c["id"] == camera
        )
        with torch.no_grad():
            g = self.model.pose(cond, posed.meshes.vertices[frame], frame)
            out = render_gaussians(
                g.means,
                g.quats,
                g.scales,
                g.opacities,
                g.colors,
                torch.tensor(view["K"], dtype=torch.float32),
                torch.tensor(view["world_to_cam"], dtype=torch.float32),
                int(view["width"]),
                int(view["height"]),
                torch.tensor(self.manifest["background"], dtype=torch.float32),
                backend=self.backend,
            )
        return out.rgb.clamp(0, 1).numpy()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of images in [0, 1]."""
    return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))
