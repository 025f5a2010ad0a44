"""The report in a real browser: headless Chromium plays its reenactment videos and draws the page.

Needs Chromium from the system packages (Debian/Ubuntu: ``apt-get install chromium``); without it the test is
skipped with that instruction. Slow: it runs the smoke DAG first (about 1.5 minutes on 2 cores).
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import pytest

from tests.conftest import run_cli

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
HAVE_ENOUGH_DATA = 4  # HTMLMediaElement.readyState
#: Appended to a copy of the page: plays every video, then writes each one's state into the DOM.
PROBE = """<script>
window.addEventListener('load', () => {
  const videos = [...document.querySelectorAll('video')];
  videos.forEach(v => { v.muted = true; v.play().catch(() => {}); });
  setTimeout(() => {
    const pre = document.createElement('pre');
    pre.id = 'probe';
    pre.textContent = JSON.stringify(videos.map(v => ({ready: v.readyState, time: v.currentTime,
                                                        error: v.error ? v.error.code : null})));
    document.body.appendChild(pre);
  }, 3000);
});
</script>"""


def _chromium(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(CHROMIUM), "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", *args],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium")
def test_report_videos_play_and_the_page_is_drawn(tmp_path: Path) -> None:
    out = tmp_path / "out"
    run = run_cli(f"paths.outputs={out}", "quality=smoke", "run.progress=false")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    report = out / "synth_a" / "methods" / "interactavatar" / "report" / "report.html"
    probe = tmp_path / "probe.html"
    probe.write_text(report.read_text() + PROBE)
    dom = _chromium(
        "--autoplay-policy=no-user-gesture-required", "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()
    )
    found = re.search(r'<pre id="probe">(.*?)</pre>', dom.stdout, re.S)
    assert found, dom.stderr[-2000:]
    videos = json.loads(html.unescape(found.group(1)))
    assert len(videos) == 3  # the held-out camera, the first train camera, the orbit
    for state in videos:
        assert state["error"] is None and state["ready"] >= HAVE_ENOUGH_DATA and state["time"] > 0, videos
    shot = tmp_path / "page.png"
    _chromium("--window-size=1280,2400", "--virtual-time-budget=5000", f"--screenshot={shot}", report.as_uri())
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (2400, 1280)
    assert image.std() > 10  # text, tables and frames: not a blank page
