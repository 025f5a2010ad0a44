"""Escaping for the web pages the project writes (the report, the browser viewer): every string that comes from a
capture, a config or a file goes through one of these where it reaches HTML or JavaScript.

- :func:`text`: HTML text (an element's content) and quoted attribute values (``alt``, ``title``);
- :func:`url_path`: a relative URL (``href``, ``src``, a data file the page loads) built from names;
- :func:`script_json`: a value written into a script (an inline ``<script>`` or a ``.js`` file) as JSON.

Names a capture gives (sequences, cameras) are also path components, which the capture's checks restrict
(:mod:`data_schemas.names`); labels, notes and captions are free text. Escaping here does not depend on those
checks: a page stays inert whatever the names are.
"""

from __future__ import annotations

import html
import json
from urllib.parse import quote

#: the characters JSON leaves as they are that can end or change an inline script (``</script>``, ``<!--``, ``&``
#: where the page is read as XML), each written as a \uXXXX escape: the same string to JSON and to JavaScript
_SCRIPT_ESCAPES = str.maketrans({c: f"\\u{ord(c):04x}" for c in "<>&"})
#: path components a URL cannot carry as names: percent-encoding does not help, browsers read ``%2E%2E`` as ``..``
_DOT_SEGMENTS = ("", ".", "..")


def text(value: object) -> str:
    """``str(value)`` for HTML text or a quoted attribute value (``<td>{}</td>``, ``alt='{}'``, ``title="{}"``):
    ``&``, ``<``, ``>``, ``"`` and ``'`` become character references. Not for a URL (:func:`url_path`) nor for a
    script (:func:`script_json`)."""
    return html.escape(str(value), quote=True)


def url_path(*components: str) -> str:
    """A relative URL of the path ``components``, each percent-encoded whole (``/``, ``?``, ``#``, ``%`` and spaces
    included) and joined by ``/``: for ``href`` and ``src`` (after a literal prefix such as ``../../``) and for the
    file names of data a page loads. The result holds only letters, digits, ``-._~%/``: it needs no further escaping
    in an HTML attribute or in JSON. Raises ValueError for an empty, ``.`` or ``..`` component, which would name
    another folder."""
    if not components or any(c in _DOT_SEGMENTS for c in components):
        raise ValueError(f"url_path{components!r}: a path component cannot be empty, '.' or '..'")
    return "/".join(quote(c, safe="") for c in components)


def script_json(value: object) -> str:
    """``value`` as JSON to write into a script, inline (``<script>x = {};</script>``) or in a ``.js`` file: ASCII
    only (every other character, U+2028 and U+2029 included, a \\uXXXX escape, so the file's encoding does not
    matter and no line separator ends a string), with no ``<``, ``>`` or ``&`` (no ``</script>`` or ``<!--`` can end
    the script); it parses (``json.loads``, JavaScript) to the same value."""
    return json.dumps(value).translate(_SCRIPT_ESCAPES)
