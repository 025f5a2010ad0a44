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
    from pipeline.config_reference import PAGE, dataset_configs, default_config, render

    assert PAGE.read_text() == render(default_config(), dataset_configs()), (
        "docs/reference/config-keys.md is stale: run `python -m pipeline.config_reference`"
    )
    assert "`stage.dynamic.d_max`" in PAGE.read_text()
    assert "## `dataset=folder`" in PAGE.read_text() and "`dataset.hand_keypoint_order`" in PAGE.read_text()


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


#: The user's pages: everything under docs/ but the dated notes and the benchmarks' own result pages (each a
#: result file as its benchmark wrote it, dated and with its commit); the generated config reference and the
#: results index are the user's and are checked.
NOTES = REPO / "docs" / "notes"
RESULT_PAGE_BANNER = "<!-- generated from benchmarks/results/"

#: An issue number: "issue 12", "issue #12", "issues 3 and 4", "the issue-40 settings", "#12" on its own (not an
#: HTML entity, a URL fragment or a word).
ISSUE_NUMBER = re.compile(r"\bissues?[ -]#?\d+|(?<![\w&#/])#\d+\b", re.IGNORECASE)

#: Phrases that narrate the project's history rather than say what is true now, each chosen because ordinary
#: prose about the software has no use for it ("used to" alone is refused only as "used to be": "is used to
#: compute" is ordinary; "the fix" alone is ordinary in "an error naming the fix", so only "before/since the fix").
HISTORY_PHRASES = re.compile(
    r"\b(?:"
    r"the issue"  # "the issue asked", "the issue's goal": which issue is history; say what is wanted now
    r"|used to be"
    r"|no longer"  # "no longer takes the batch down": say what it does
    r"|(?:was|were|has been|have been) (?:changed|renamed|moved|removed|replaced|reverted)"
    r"|(?:before|since|until) the (?:fix|change|refactor|move)"
    r"|the refactor"
    r"|round \d+"
    r"|(?:this|that|an earlier|a later|the previous) session"
    r"|not (?:been )?re-?measured"
    r"|moved from the README"
    r"|the (?:previous|earlier) (?:build|version|code)"
    r"|today's"  # "today's draft": name the setting
    r")\b",
    re.IGNORECASE,
)


def user_pages() -> list:
    pages = []
    for path in sorted((REPO / "docs").rglob("*.md")):
        if NOTES in path.parents or path.read_text().startswith(RESULT_PAGE_BANNER):
            continue
        pages.append(path)
    return pages


def history_in(text: str) -> list[tuple[int, str]]:
    """(line number, what matched) for every issue number and history phrase in ``text``."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for pattern in (ISSUE_NUMBER, HISTORY_PHRASES):
            found += [(number, m.group(0)) for m in pattern.finditer(line)]
    return found


@pytest.mark.parametrize(
    "text",
    [
        "as issue 39 asked",
        "issue #12",
        "issues 3 and 4",
        "the issue-40 settings",
        "see #17",
        "The issue's goal is met",
        "it used to be slower",
        "a worker no longer takes the batch down",
        "the default was changed to 500",
        "as before the fix",
        "since the refactor",
        "in round 3",
        "measured in an earlier session",
        "not re-measured yet",
        "at today's draft",
        "agrees with the previous build",
    ],
)
def test_the_history_rules_catch_history(text):
    assert history_in(text), text


@pytest.mark.parametrize(
    "text",
    [
        "tissue shear: neighbouring displacements alike",
        "the key is used to compute the digest",
        "an error naming the fix",
        "the old artifact or none",
        "[the report](#reading-the-report) and `.locks/<stage>#<key>.lock`",
        "&#39; is an apostrophe",
        "measured with the code of 75d5127 on 2026-12-03",
        "a stage reruns when its code version changed: 7 -> 8",
    ],
)
def test_the_history_rules_leave_ordinary_prose(text):
    assert history_in(text) == [], text


def test_the_user_pages_leave_history_to_the_notes():
    """The manual says what the software does and what was measured; issue numbers and the story of the work
    belong in docs/notes/ (dated), linked from where they matter."""
    pages = user_pages()
    assert REPO / "docs" / "index.md" in pages and REPO / "docs" / "results" / "index.md" in pages
    found = [
        f"{path.relative_to(REPO)}:{line}: {match!r}" for path in pages for line, match in history_in(path.read_text())
    ]
    assert found == [], "history in the user's pages (move it to a dated note in docs/notes/):\n" + "\n".join(found)


def test_the_stage_lists_name_every_stage_in_order():
    """`interactavatar --help` and the first-run tutorial list the DAG's stages, in the registry's order."""
    from stages import REGISTRY

    names = [s.name for s in REGISTRY]
    help_page = (REPO / "conf" / "hydra" / "help" / "interactavatar.yaml").read_text()
    listed = re.search(r"DAG of stages: ([a-z, \n]+)\.", help_page)
    assert listed and [n.strip() for n in listed.group(1).split(",")] == names, "conf/hydra/help/interactavatar.yaml"
    first_run = (REPO / "docs" / "tutorials" / "first-run.md").read_text()
    listed = re.search(r"In\s+order: ((?:`[a-z]+`,?\s*)+)\.", first_run)
    assert listed and re.findall(r"`([a-z]+)`", listed.group(1)) == names, "docs/tutorials/first-run.md"


#: a config key named in backticks (``stage.dynamic.restarts``, ``run.threads=1``), not a file name (``run.md``)
CONFIG_KEY = re.compile(
    r"`[^`\n]*?\b((?:stage|run|fit|quality|dataset|model|method|paths|reenact)\.[A-Za-z0-9_.]*[A-Za-z0-9_])"
    r"(?!\.\w|\w|\*)"
)
FILE_SUFFIXES = (".md", ".yaml", ".json", ".py", ".parquet", ".png", ".ply", ".html", ".js", ".txt", ".mp4")
#: a path of the repository named in backticks (``tests/.../test_x.py``; globs, ``<name>`` placeholders and
#: ``{md,json}`` alternatives allowed)
REPO_PATH = re.compile(r"`((?:tests|benchmarks|avatar|pipeline|stages|data_schemas|reporting|importers|conf)/[^`\s:]+)")


def _config_keys() -> set[str]:
    from omegaconf import OmegaConf

    from tests.conftest import compose_cfg

    def keys(node, prefix: str) -> set[str]:
        found = set()
        for key in node.keys() if OmegaConf.is_dict(node) else ():
            path = f"{prefix}.{key}" if prefix else str(key)
            found |= {path} | keys(node._get_node(key), path)
        return found

    return set().union(*(keys(compose_cfg(o), "") for o in ([], ["dataset=folder"], ["dataset=decaf"])))


def test_every_config_key_and_repository_path_a_user_page_names_exists():
    """A key the manual tells a user to set, or a file it points to, that does not exist costs them an hour: every
    backticked config key of the README and the user's pages is a key of the composed config (with any dataset), and
    every backticked path of the repository exists (a glob or a ``{a,b}`` alternative matches something)."""
    known, missing = _config_keys(), []
    for page in [REPO / "README.md", *user_pages()]:
        text = page.read_text()
        for key in CONFIG_KEY.findall(text):
            if not key.endswith(FILE_SUFFIXES) and key not in known:
                missing.append(f"{page.relative_to(REPO)}: config key {key}")
        for path in REPO_PATH.findall(text):
            path = path.rstrip(".,;)")
            pattern = re.sub(r"<[^>]+>", "*", path)  # a placeholder: <name>, <target>
            head, brace, rest = pattern.partition("{")
            alternatives, _, tail = rest.partition("}")
            options = [head + alt + tail for alt in alternatives.split(",")] if brace else [pattern]
            if not any(list(REPO.glob(option)) for option in options):
                missing.append(f"{page.relative_to(REPO)}: path {path}")
    assert missing == [], "the manual names what does not exist:\n" + "\n".join(missing)


STATUS = ("<!-- status:begin -->", "<!-- status:end -->")


def _status_block(page) -> str:
    text = page.read_text()
    assert text.count(STATUS[0]) == 1 and text.count(STATUS[1]) == 1, f"{page}: one status block"
    return text.split(STATUS[0])[1].split(STATUS[1])[0]


def test_the_status_and_limitations_agree_with_the_result_files_they_cite():
    """The README's and the index's 'Status and limitations' say what does not work yet; each claim is checked
    against the result file it cites, so a GPU run or a new tracking measurement makes this fail until the words
    follow."""
    import json

    gpu = json.loads((REPO / "benchmarks" / "results" / "bench_gpu.json").read_text())
    on_gpu = [run["date"] for run in gpu["runs"] if run.get("training_device", "cpu") != "cpu"]
    tracking = json.loads((REPO / "benchmarks" / "results" / "bench_test_tracking.json").read_text())["runs"][-1]
    (table,) = [t for t in tracking["tables"] if t["title"].startswith("Each arm minus 'ground truth'")]
    drops = {
        name: [abs(float(row[table["columns"].index(name)])) for row in table["rows"]] for name in ("NV", "SR tracker")
    }
    blocks = [_status_block(REPO / "README.md"), _status_block(REPO / "docs" / "index.md")]
    assert blocks[0].replace("docs/results/", "results/") == blocks[1]  # the same words in both
    status = " ".join(blocks[0].split())
    assert ("has not run on a GPU yet" in status) == (not on_gpu), f"bench_gpu.json trained on a GPU on {on_gpu}"
    held_out = re.search(
        r"held-out motion scores (\d+\.\d)-(\d+\.\d) dB below .* held-out camera (\d+\.\d)-(\d+\.\d) dB", status
    )
    assert held_out, status
    stated = [float(x) for x in held_out.groups()]
    measured = [min(drops["SR tracker"]), max(drops["SR tracker"]), min(drops["NV"]), max(drops["NV"])]
    assert stated == [round(x, 1) for x in measured], (stated, measured)


def test_every_make_target_a_page_names_exists():
    """``make <target>`` in a code span or a code block of the README or a user page is a target of the Makefile."""
    targets = set(re.findall(r"^([a-zA-Z][\w-]*):", (REPO / "Makefile").read_text(), re.M))
    named = re.compile(r"(?:`|^\s*)make ([a-z][a-z0-9-]*)", re.M)
    missing = [
        f"{page.relative_to(REPO)}: make {target}"
        for page in [REPO / "README.md", *user_pages()]
        for target in named.findall(page.read_text())
        if target not in targets
    ]
    assert missing == [], "the manual names Makefile targets that do not exist:\n" + "\n".join(missing)
