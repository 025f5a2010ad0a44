"""Hostile names stay text (issue 52, item 1 and item 8's first point): the report and the viewer page, written by
their own section builders and writer from a capture, a config and files whose every name tries to break out of
its HTML, attribute, URL or script, hold no live markup, and in headless Chromium no payload runs, no element is
made from one, each name reads back as the text it was and the viewer loads its data and ground truth through
percent-encoded URLs.

The builders are called directly (no DAG: a few seconds in all), so the escaping is tested whatever the capture's
own checks refuse as ids (data_schemas/names.py). The Chromium tests need Debian's chromium (``make browser``) and,
for the viewer, the page's bundle (``make viewer``); without them they are skipped saying so.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np
import pytest

from avatar.artifacts.motion import PosedSequence
from avatar.viewer.codec import CodecConfig
from avatar.viewer.page import Motion, PageSettings, write_viewer
from benchmarks.viewer_browser import ViewerPage, chromium, manifest, open_viewer
from data_schemas.cameras import Camera
from data_schemas.capture import SequenceInfo
from data_schemas.metrics import COMPARISON, METRICS
from data_schemas.tables import write_table
from data_schemas.web_escape import url_path
from pipeline.manifest import MANIFEST_NAME
from reporting.capture import cameras_table, contact_paragraph, contact_sheet_section, intro, stages_table
from reporting.comparison import comparison_section
from reporting.evaluation import metrics_section, renders_section
from reporting.fit import fit_section
from reporting.html import image_png, page, png_image
from reporting.reenact import reenact_section, viewer_section
from reporting.scene import pbd_section, scene_section
from reporting.training import dynamic_summary
from tests.viewer.conftest import NEEDS_BROWSER
from tests.viewer.toy_viewer import BACKGROUND, CAMERAS, SIZE, K, NoConditioning, toy_avatar, toy_meshes

#: a name that can be a file name (no '/'), trying every way out: quotes closing an attribute, tags with handlers,
#: a percent-escape and a reference to be decoded twice, URL delimiters, a JavaScript line separator
NAME = "'\"><img src=x onerror=window.__pwned=1><svg onload=window.__pwned=2>#?%41&amp;\u2028end"
#: free text (labels, notes, captions): the name, and a script end and a comment start
TEXT = NAME + "</script><script>window.__pwned=3</script><!--"
#: a second hostile name (a second camera, a second sequence, another method)
OTHER = NAME + " 2"
#: a motion named as an Object.prototype member: the page's lookups by name must not find the prototype's
PROTOTYPE_NAME = "constructor"
NEEDS_CHROMIUM, NEEDS_BUNDLE = NEEDS_BROWSER  # chromium; chromium and the page's bundle
#: what the browser is asked after loading a page: did anything run, what did the payloads make (the viewer's own
#: script has an onerror), which scripts are there, and the page's text
PROBE = """() => ({
  pwned: window.__pwned === undefined ? null : window.__pwned,
  made: document.querySelectorAll('img[src="x"], svg, [onload], :not(script)[onerror]').length,
  scripts: [...document.scripts].map(s => s.getAttribute('src')),
  text: document.body.textContent,
})"""


def _json(path: Path, value: object) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value))
    return path


def _png(path: Path) -> Path:
    """A 1x1 PNG at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(base64.b64decode(image_png(np.zeros((1, 1, 3), np.uint8))))
    return path


def _manifest(metrics: dict[str, Any], config: dict[str, Any] | None = None) -> dict[str, Any]:
    """A stage's run record (pipeline/manifest.py) as the report reads it."""
    return {
        "timings": {"wall_s": 1.0},
        "peak_memory_mb": 10.0,
        "metrics": metrics,
        "created": TEXT,
        "config": config or {},
    }


def _scene(root: Path) -> Path:
    why = {k: TEXT for k in ("model_hand", "model_pbd", "model_interaction")}
    flags = {"model_hand": False, "model_pbd": False, "model_interaction": False}
    body = {**flags, "why": why, "deforming_triangles": [], "face_triangles": 4, "d_max_m": 0.01, "decided_on": NAME}
    _json(root / "scene.json", {**body, "hand_triangles": 2})
    return root


def _fit(root: Path) -> Path:
    entry = {"mpjpe_hand_mm": 1.0, "weak_frames": {NAME: [1]}, "reprojection_px": {"hand": 2.0}}
    refinement = {
        "silhouette_iou": {"keypoint_fit": {"face": {NAME: 0.5}}, "refined": {"face": {NAME: 0.6}}},
        "moved_mm": {"face": [1.0]},
        "rotated_deg": {"face": [0.5]},
    }
    sequences = {NAME: {**entry, "keypoint_fit": entry, "refinement": refinement}}
    _json(root / "fit_report.json", {"source": TEXT, "refine": TEXT, "sequences": sequences})
    _png(root / NAME / "refinement.png")
    return root


def _pbd(root: Path) -> Path:
    frames = [{"simulated": True, "near": True, "penetration_max_mm": 0.1, "max_offset_mm": 1.0}]
    body = {"source": TEXT, "stiffness": TEXT, "frame_convention": TEXT, "sequences": {NAME: {"frames": frames}}}
    _json(root / "pbd_report.json", body)
    return root


def _evaluate(root: Path) -> Path:
    root.mkdir(parents=True)
    one = np.ones(1, np.float32)
    write_table(
        root / "metrics.parquet",
        METRICS,
        {
            "method": [TEXT],
            "split": ["novel_view"],
            "camera_id": [NAME],
            "frame": np.zeros(1, np.int32),
            "region": ["full"],
            "contact": np.zeros(1, bool),
            "psnr": one,
            "ssim": one,
            "lpips": one,
        },
    )
    return root


def _reenact(root: Path) -> Path:
    info = {
        "driver": TEXT,
        "frames": 1,
        "head_scale": 1.0,
        "pbd": {"simulated": False, "frames": []},
        "transfer": {"placement": TEXT, "frames": [{"touching_points": 3}]},
        "sequence_note": TEXT,
        "ground_truth": {"sequence": NAME, "cameras": [NAME, OTHER]},
    }
    _json(root / "reenact_report.json", info)
    metrics = {"frames_per_second": 1.0, "image_size": TEXT, "model_ms_per_frame": 1.0, "render_ms_per_view": 1.0}
    _json(root / MANIFEST_NAME, _manifest({**metrics, "transfer_kept_fraction": 0.5, "transfer_residual_mm": 1.0}))
    for stem in (NAME, f"{OTHER}_vs_gt", OTHER):
        (root / "videos").mkdir(exist_ok=True)
        (root / "videos" / f"{stem}.mp4").write_bytes(b"not a video")
    return root


def _viewer(methods: Path) -> Path:
    """This method's viewer folder among those of methods named hostile."""
    own = methods / "own" / "viewer"
    info = {"page_built": False, "build_command": TEXT, "gaussians": TEXT, "bytes_per_frame": 1.0}
    _json(own / "viewer.json", {**info, "mb_per_100_frames": 1.0})
    for name in (NAME, OTHER):
        (methods / name / "viewer").mkdir(parents=True)
        (methods / name / "viewer" / "index.html").write_text("<title>other</title>")
    return own


def _compare(root: Path) -> Path:
    tables = [{"title": TEXT, "headers": [TEXT], "rows": [[TEXT]]}]
    _json(root / "tables.json", {"tables": tables, "notes": [TEXT]})
    _png(root / "figures" / f"{NAME}.png")
    row: dict[str, Any] = {"method": [NAME], "label": [TEXT], "split": ["novel_view"], "region": ["full"]}
    row |= {"contact": ["all"], "seed": np.zeros(1, np.int32), "images": np.ones(1, np.int32)}
    row |= {k: np.ones(1, np.float32) for k in ("psnr", "ssim", "lpips", "train_wall_s")}
    write_table(root / "comparison.parquet", COMPARISON, {**row, "train_steps": [1], "gaussians": np.ones(1, np.int64)})
    return root


def hostile_report(root: Path) -> str:
    """The report's page from every section builder that shows a name, each fed hostile names and text."""
    sequence = SequenceInfo(3, 25.0, 8, 8, has_masks=False, has_ground_truth=False, notes=(TEXT,))
    camera = Camera(NAME, 8, 8, np.asarray(K), np.eye(4), np.zeros(5), TEXT)
    manifests = {NAME: _manifest({NAME: TEXT}), "pbd": _manifest({}), "dynamic": _manifest({"steps": TEXT})}
    manifests["warmup"] = _manifest({}, {"quality.gaussians_per_triangle": 1})
    png = image_png(np.zeros((2, 2, 3), np.uint8))
    return page(
        [
            intro(TEXT, NAME, TEXT, TEXT, TEXT, {NAME: sequence, OTHER: sequence}, 2),
            contact_paragraph({NAME: (1, 3, TEXT)}),
            scene_section(_scene(root / "scene"), manifests),
            stages_table(manifests),
            cameras_table([camera]),
            fit_section(_fit(root / "fit")),
            pbd_section(_pbd(root / "pbd")),
            metrics_section(_evaluate(root / "evaluate")),
            reenact_section(_reenact(root / "reenact")),
            viewer_section(_viewer(root / "methods")),
            comparison_section(_compare(root / "compare")),
            dynamic_summary({"metrics": {"steps": TEXT, "ms_per_step": 1.0}}),
            contact_sheet_section(NAME, 0, TEXT, png),
            renders_section(TEXT, _png(root / "grids" / "novel_view.png").parent),
            png_image(TEXT, png),
        ]
    )


def hostile_viewer(out_dir: Path, frames: int = 3) -> None:
    """The toy avatar's viewer (tests/viewer/toy_viewer.py) with hostile motion names, labels, camera ids and
    identity, ground truth on the first motion."""
    meshes, rest = toy_meshes(frames)
    avatar = toy_avatar(meshes, rest)
    cameras = [
        {"id": name, "K": K, "world_to_cam": w2c.tolist(), "width": SIZE, "height": SIZE}
        for name, w2c in zip((NAME, OTHER), CAMERAS.values())
    ]
    truth = np.full((frames, len(cameras), SIZE, SIZE, 3), 128, np.uint8)
    motions = [
        Motion(
            name,
            TEXT,
            PosedSequence({}, meshes, np.zeros((frames, 144, 3))),
            NoConditioning(),  # type: ignore[arg-type]  # the toy's pose reads none
            np.arange(frames) % 2 == 1,
            cameras,
            ground_truth,
            BACKGROUND,
        )
        for name, ground_truth in ((NAME, truth), (PROTOTYPE_NAME, None))
    ]
    out_dir.mkdir(parents=True)
    identity = {"method": NAME, "label": TEXT, "subject": TEXT}
    write_viewer(out_dir, avatar, motions, CodecConfig(), PageSettings(), identity)


def _assert_inert(html: str) -> None:
    """No payload of :data:`TEXT` is left as markup in ``html``."""
    for payload in ("<img src=x", "<svg", "<script", "<!--", "\"'>"):
        assert payload not in html, payload


def test_the_reports_sections_escape_every_name(tmp_path: Path) -> None:
    page = hostile_report(tmp_path)
    _assert_inert(page)
    assert f"href='../../{url_path(NAME, 'viewer', 'index.html')}'" in page  # a link to a method named hostile


def test_the_viewers_data_scripts_hold_no_markup_and_parse(tmp_path: Path) -> None:
    hostile_viewer(tmp_path / "viewer")
    scripts = list((tmp_path / "viewer" / "data").glob("*.js"))
    expected = {"avatar.js", "manifest.js", f"motion-{NAME}.js", f"motion-{PROTOTYPE_NAME}.js"}
    assert {p.name for p in scripts} == expected
    for path in scripts:
        written = path.read_text()
        assert written.isascii() and not set("<>&") & set(written), path
    page = manifest(tmp_path / "viewer")
    assert (page["label"], page["motions"][0]["name"]) == (TEXT, NAME)
    assert page["motions"][0]["file"] == url_path("data", f"motion-{NAME}.js")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as running:
        yield running


@NEEDS_CHROMIUM
def test_no_payload_runs_in_the_report(browser: Any, tmp_path: Path) -> None:
    page_file = tmp_path / "methods" / "own" / "report" / "report.html"
    page_file.parent.mkdir(parents=True)
    page_file.write_text(hostile_report(tmp_path))
    page = browser.new_page()
    try:
        page.goto(page_file.as_uri())
        page.wait_for_timeout(300)  # image errors and loads fire
        found = page.evaluate(PROBE)
        hrefs = page.eval_on_selector_all("a", "links => links.map(a => a.href)")
    finally:
        page.close()
    assert found["pwned"] is None and found["made"] == 0 and found["scripts"] == []
    assert found["text"].count(TEXT) >= 10 and NAME in found["text"]  # each reads as it was written
    other = (tmp_path / "methods" / NAME / "viewer" / "index.html").as_uri()
    assert other in hrefs  # the link leads to the method's folder, its name percent-encoded once


@pytest.fixture
def hostile_page(browser: Any, tmp_path: Path) -> Iterator[ViewerPage]:
    viewer_dir = tmp_path / "viewer"
    hostile_viewer(viewer_dir)
    with open_viewer(browser, f"{(viewer_dir / 'index.html').as_uri()}?scale=1") as viewer:
        yield viewer


@NEEDS_CHROMIUM
@NEEDS_BUNDLE
def test_no_payload_runs_in_the_viewer_and_its_urls_are_encoded(hostile_page: ViewerPage) -> None:
    page = hostile_page.page
    assert hostile_page.errors == [] and not page.evaluate("window.viewerFailed === true")
    found = page.evaluate(PROBE)
    assert found["pwned"] is None and found["made"] == 0
    motion_script = url_path("data", f"motion-{NAME}.js")
    assert sorted(found["scripts"]) == sorted(["data/manifest.js", "viewer.js", "data/avatar.js", motion_script])
    assert page.eval_on_selector_all("#motion option", "o => o.map(e => e.textContent)") == [TEXT, TEXT]
    assert page.eval_on_selector_all("#camera option", "o => o.map(e => e.textContent)") == [NAME, OTHER]
    assert page.text_content("#render-caption").startswith(f"{TEXT}, {TEXT}")
    gt = page.get_attribute("#gt", "src")  # encodeURIComponent: as url_path but for !'()*
    assert [unquote(c) for c in gt.split("/")] == ["data", "gt", NAME, NAME, "00000.jpg"]
    page.wait_for_function("document.getElementById('gt').complete")
    assert page.evaluate("document.getElementById('gt').naturalWidth") == SIZE  # the encoded URL finds the file
    hostile_page.show(PROTOTYPE_NAME, 1, OTHER)  # a motion named as an Object.prototype member loads
    assert hostile_page.state()["motion"] == PROTOTYPE_NAME and not page.is_visible("#gt")
    assert page.evaluate(PROBE)["pwned"] is None
