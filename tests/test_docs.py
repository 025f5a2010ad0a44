"""The front door and the manual: a short README whose links resolve, a documentation site that builds
strictly, and the generated pages (the config reference, the README's results table) equal to what their
sources say now."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from tests.conftest import REPO


def test_readme_is_a_front_door():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; the manual is docs/"
    text = "\n".join(lines)
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if not target.startswith("http"):
            assert (REPO / target).exists(), f"README.md links to {target}, which does not exist"
    for words in ("make run", "make test", "dataset=folder", "@inproceedings", "Licence"):
        assert words in text


def test_the_config_reference_matches_conf_and_the_schemas():
    from pipeline.config_reference import PAGE, default_config, render

    assert PAGE.read_text() == render(default_config()), (
        "docs/reference/config-keys.md is stale: run `python -m pipeline.config_reference`"
    )
    assert "`stage.dynamic.d_max`" in PAGE.read_text()


def test_the_results_pages_match_the_committed_data():
    """The README's results table and docs/results/ are rendered from benchmarks/results/, never typed."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import render_results
    finally:
        sys.path.pop(0)
    stale = [
        str(p.relative_to(REPO))
        for p, text in render_results.rendered().items()
        if not p.is_file() or p.read_text() != text
    ]
    assert stale == [], f"stale generated pages {stale}: run `python benchmarks/render_results.py`"
    assert "| (a) full appearance" in (REPO / "README.md").read_text()


def test_the_documentation_site_builds_strictly(tmp_path):
    """mkdocs build --strict: a broken link, a page missing from the navigation or a missing page fails it."""
    mkdocs = REPO / ".venv" / "bin" / "mkdocs"
    command = [str(mkdocs)] if mkdocs.exists() else [sys.executable, "-m", "mkdocs"]
    if subprocess.run([*command, "--version"], capture_output=True).returncode != 0:
        pytest.fail("mkdocs is not installed: `make test` installs it (the `test` extra)")
    done = subprocess.run(
        [*command, "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        timeout=300,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert (tmp_path / "site" / "reference" / "config-keys" / "index.html").is_file()
