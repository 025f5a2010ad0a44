"""data_schemas.web_escape: the one escaping of names where they reach HTML, URLs and scripts (issue 52)."""

from __future__ import annotations

import json
import re
from urllib.parse import unquote

import pytest

from data_schemas.web_escape import script_json, text, url_path

#: strings a capture, a config or a file could hold, each trying to leave its context
HOSTILE = (
    "<img src=x onerror=alert(2)>",
    "</script><script>window.__pwned = 1</script>",
    "<!--",
    "\"'><svg onload=alert(1)>",
    "a & b; &amp; &#60;",
    "line\u2028separator\u2029paragraph",
    "#?%2e%2e/../ back\\slash",
    "ünïcödé 👋",
)


def test_text_escapes_markup_and_both_quotes() -> None:
    assert text("<img src=x onerror=alert(2)>") == "&lt;img src=x onerror=alert(2)&gt;"
    assert text("\"'&") == "&quot;&#x27;&amp;"
    assert text(3.5) == "3.5"


@pytest.mark.parametrize("value", HOSTILE)
def test_text_leaves_no_markup_character(value: str) -> None:
    escaped = text(value)
    assert not set("<>\"'") & set(escaped)
    assert re.sub(r"&(lt|gt|quot|#x27|amp);", "", escaped).count("&") == 0  # every & starts a reference


def test_url_path_encodes_each_component_whole() -> None:
    assert url_path("data", "gt", "a b", "c#d?e", "f/g", "00001.jpg") == "data/gt/a%20b/c%23d%3Fe/f%2Fg/00001.jpg"
    assert url_path("<x>", "'\"&%") == "%3Cx%3E/%27%22%26%25"
    assert url_path("motion-train.js") == "motion-train.js"


@pytest.mark.parametrize("value", HOSTILE)
def test_url_path_is_inert_in_html_and_decodes_to_the_name(value: str) -> None:
    url = url_path("data", value, "index.html")
    assert re.fullmatch(r"[A-Za-z0-9._~%/-]+", url)
    assert [unquote(c) for c in url.split("/")] == ["data", value, "index.html"]


@pytest.mark.parametrize("components", [(), ("a", ".."), (".",), ("a", "", "b")])
def test_url_path_refuses_dot_segments_and_empty_components(components: tuple[str, ...]) -> None:
    with pytest.raises(ValueError, match="cannot be empty"):
        url_path(*components)


def test_script_json_closed_form() -> None:
    assert script_json({"label": "</script>"}) == '{"label": "\\u003c/script\\u003e"}'
    assert script_json("a&b\u2028") == '"a\\u0026b\\u2028"'
    assert script_json([1, 2.5, None, True]) == "[1, 2.5, null, true]"


@pytest.mark.parametrize("value", HOSTILE)
def test_script_json_round_trips_and_cannot_end_a_script(value: str) -> None:
    data = {value: [value, {"name": value}], "n": 1}
    written = script_json(data)
    assert json.loads(written) == data
    assert written.isascii()
    assert not set("<>&\u2028\u2029") & set(written)
