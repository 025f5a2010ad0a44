"""``interactavatar-view`` serves its folder and nothing else: no file outside it (links resolved), no dot-folder,
no listing, no request addressed to another host; bad ports are one line."""

from __future__ import annotations

import os
import random
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

import pytest

from pipeline import view

SENTINEL = b"SENTINEL-5f0c1e9a-outside-the-served-folder"
PAGE = b"<!doctype html><title>viewer</title><script src='viewer.js'></script>"
INSIDE = {
    "methods/toy/viewer/index.html": PAGE,
    "methods/toy/viewer/viewer.js": b"window.viewer = {};",
    "methods/toy/viewer/data/manifest.js": b"window.manifest = {};",
    "methods/toy/viewer/data/gt/cam0 #1/0001.jpg": b"\xff\xd8\xff\xe0 jpeg",
    "methods/toy/viewer/data/caf\u00e9.js": b"window.cafe = 1;",
    "methods/toy/report/report.html": b"<a href='../viewer/index.html'>viewer</a>",
    "methods/other/viewer/index.html": b"<!doctype html><title>other</title>",
}
HIDDEN = {
    ".locks/capture.lock": b"lock",
    ".cache/sources.json": b'{"secret": "sources"}',
    ".tmp/fit-1/partial.ply": b"partial",
    "methods/toy/viewer/.notes": b"notes",
}


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A served folder holding ``INSIDE`` and ``HIDDEN`` and links into and out of it, and the sentinel file outside
    it that those links reach."""
    base = tmp_path_factory.mktemp("view")
    root, outside = base / "served", base / "outside"
    for name, content in {**INSIDE, **HIDDEN}.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(content)
    outside.mkdir()
    (outside / "secret.txt").write_bytes(SENTINEL)
    (outside / "index.html").write_bytes(SENTINEL)
    links = {
        "outdir": outside,  # a folder outside (`ln -s /etc etcdir`)
        "up": base,  # the folder above
        "methods/toy/viewer/data/leak.js": outside / "secret.txt",  # a file outside
        "methods/toy/viewer/data/gt/cam1": outside,  # a folder outside, deep inside
        "methods/abs": Path("/"),
        "hidden": root / ".cache",  # inside, but a dot-folder
        "loop": root / "loop",
        "alias": root / "methods/toy/viewer",  # inside: may be served
    }
    for name, target in links.items():
        (root / name).symlink_to(target)
    return root, outside


@pytest.fixture(scope="module")
def port(tree: tuple[Path, Path]) -> Iterator[int]:
    """The port of a running server of the tree's folder."""
    server = view.serve(tree[0])
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()
    thread.join()


def fetch(port: int, path: bytes | str, method: str = "GET", host: str | None = "") -> tuple[int, bytes, bytes]:
    """The status, headers and body of a raw HTTP/1.0 request for ``path`` (sent as is); ``host`` "" is the server's
    own address, None sends no Host header."""
    target = path.encode() if isinstance(path, str) else path
    lines = [method.encode() + b" " + target + b" HTTP/1.0"]
    if host is not None:
        lines.append(b"Host: " + (host or f"127.0.0.1:{port}").encode())
    with socket.create_connection(("127.0.0.1", port), timeout=10) as connection:
        connection.sendall(b"\r\n".join(lines) + b"\r\n\r\n")
        response = b"".join(iter(lambda: connection.recv(65536), b""))
    assert response.startswith(b"HTTP/"), f"no answer to {target!r}"
    head, _, body = response.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), head, body


def answer(port: int, path: str, host: str | None = "") -> tuple[int, bytes]:
    """The status and body of a GET of ``path``."""
    status, _, body = fetch(port, path, host=host)
    return status, body


def url(name: str) -> str:
    """The request path of a file ``name`` relative to the served folder, as a browser encodes it."""
    return "/" + quote(name)


def test_every_file_inside_is_served(port: int) -> None:
    for name, content in INSIDE.items():
        status, _, body = fetch(port, url(name))
        assert (status, body) == (200, content), name


def test_a_link_inside_to_inside_is_served(port: int) -> None:
    assert answer(port, "/alias/index.html") == (200, PAGE)


@pytest.mark.parametrize(
    "path",
    [
        "/outdir/secret.txt",
        "/outdir/",
        "/outdir/index.html",
        "/up/outside/secret.txt",
        "/methods/toy/viewer/data/leak.js",
        "/methods/toy/viewer/data/gt/cam1/secret.txt",
        "/methods/abs/etc/passwd",
        "/loop",
        "/loop/x",
    ],
)
def test_a_link_that_leaves_the_folder_is_refused(port: int, path: str) -> None:
    status, head, body = fetch(port, path)
    assert status in (403, 404) and SENTINEL not in head + body and b"root:" not in body


@pytest.mark.parametrize("path", [url(name) for name in HIDDEN] + ["/.locks/", "/.cache/", "/hidden/sources.json"])
def test_dot_folders_and_dot_files_are_hidden(port: int, path: str) -> None:
    status, _, body = fetch(port, path)
    assert status == 404 and b"secret" not in body and b"capture.lock" not in body


@pytest.mark.parametrize("path", ["/", "/methods/", "/methods/toy/", "/methods/toy/viewer/data/"])
def test_a_folder_is_never_listed(port: int, path: str) -> None:
    status, _, body = fetch(port, path)
    assert status == 404 and b"viewer" not in body and b"manifest" not in body and b"report" not in body


def test_a_folder_with_an_index_serves_it(port: int) -> None:
    assert answer(port, "/methods/toy/viewer/") == (200, PAGE)
    status, head, _ = fetch(port, "/methods/toy/viewer?motion=test")
    assert status == 301 and b"\r\nLocation: /methods/toy/viewer/?motion=test" in head


def test_a_query_is_not_part_of_the_file_name(port: int) -> None:
    assert answer(port, "/methods/toy/viewer/index.html?motion=test&frame=5") == (200, PAGE)


@pytest.mark.parametrize(
    "host",
    [
        None,
        "evil.example",
        "evil.example:{port}",
        "127.0.0.1",
        "localhost",
        "127.0.0.1:{other}",
        "localhost:{other}",
        "127.0.0.1.evil.example:{port}",
        "[::1]:{port}",
        "0.0.0.0:{port}",
        "127.0.0.1:{port}\r\nHost: evil.example",
        "127.0.0.1:{port}@evil.example",
    ],
)
def test_a_request_for_another_host_is_refused(port: int, host: str | None) -> None:
    named = None if host is None else host.format(port=port, other=port + 1)
    status, _, body = fetch(port, "/methods/toy/viewer/index.html", host=named)
    assert status in (403, 421) and PAGE not in body and 0 < len(body) < 1000


@pytest.mark.parametrize("host", ["127.0.0.1:{port}", "localhost:{port}"])
def test_the_servers_own_address_is_answered(port: int, host: str) -> None:
    assert answer(port, "/methods/toy/viewer/index.html", host.format(port=port)) == (200, PAGE)


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "PROPFIND"])
def test_only_get_and_head_are_answered(port: int, method: str) -> None:
    status, _, body = fetch(port, "/methods/toy/viewer/index.html", method=method)
    assert status in (405, 501) and PAGE not in body


def test_head_sends_the_headers_without_the_file(port: int) -> None:
    status, head, body = fetch(port, "/methods/toy/viewer/index.html", method="HEAD")
    assert status == 200 and body == b"" and f"Content-Length: {len(PAGE)}".encode() in head


@pytest.mark.parametrize("path", ["/methods/toy/viewer/index.html", "/methods/toy/viewer/viewer.js", "/nothing"])
def test_responses_carry_the_headers_of_a_local_static_server(port: int, path: str) -> None:
    _, head, _ = fetch(port, path)
    for header in (
        b"X-Content-Type-Options: nosniff",
        b"Referrer-Policy: no-referrer",
        b"Cache-Control: no-store",
        b"Cross-Origin-Resource-Policy: same-origin",
    ):
        assert b"\r\n" + header + b"\r\n" in head + b"\r\n", header


def fuzzed_paths(tree: tuple[Path, Path], count: int, seed: int = 52) -> list[bytes]:
    """``count`` request paths mixing traversal spellings, encodings, separators, links and odd names."""
    root, outside = tree
    pieces = [
        *["..", "%2e%2e", "%2E%2e", ".%2e", "%2e.", "...", ".", "%2e", "%252e%252e", "%c0%ae%c0%ae", "..;"],
        *["%2f", "%2F", "%5c", "%5C", "\\", "/", "//", "%00", "\x00", "%0a", ";", "?", "#", "%3f", "%23"],
        *["outdir", "up", "outside", "secret.txt", "leak.js", "hidden", "loop", "alias", "abs", "etc", "passwd"],
        *["methods", "toy", "viewer", "data", "gt", "cam1", "index.html", ".locks", ".cache", "sources.json"],
        *["caf\u00e9.js", "caf%C3%A9.js", "%ff%fe", "\u202e", "\U0001f600", "a" * 300, "%41" * 200, "~", "%"],
        *[str(outside), str(outside / "secret.txt"), str(root), "/etc/passwd", "file:", "http://evil.example/"],
    ]
    legitimate = [url(name).split("/") for name in INSIDE] + [["", "alias", "index.html"], ["", "methods", "toy", ""]]
    separators = ["/", "/", "/", "", "%2f", "\\", "//"]
    rng = random.Random(seed)
    paths = []
    for _ in range(count):
        if rng.random() < 0.5:  # a legitimate path with a piece put in, or put in place of one of its names
            names = list(rng.choice(legitimate))
            at = rng.randrange(1, len(names) + 1)
            names[at : at + rng.randint(0, 1)] = [rng.choice(pieces) + rng.choice(separators[:-3])]
            path = "/".join(names)
        else:
            words = rng.choices(pieces, k=rng.randint(1, 8))
            start = rng.choice(["/", "/", "//", "", "/./", "/../", str(outside) + "/", "/outdir/", "/up/"])
            path = start + "".join(word + rng.choice(separators) for word in words)
        paths.append(path.encode("utf-8", "surrogatepass"))
    return paths


def test_fuzzed_paths_never_reach_outside_nor_fail(port: int, tree: tuple[Path, Path]) -> None:
    served = 0
    for path in fuzzed_paths(tree, 1500):
        status, head, body = fetch(port, path)
        assert SENTINEL not in head + body, path
        assert status < 500, path
        assert not any(hidden in body for hidden in HIDDEN.values()), path
        for line in head.split(b"\r\n"):
            if line.lower().startswith(b"location:"):
                assert line[10:].startswith(b"/") and line[10:12] not in (b"//", b"/\\"), path  # no open redirect
        served += status == 200
    assert served > 0  # some paths were legitimate: the fuzz reached files
    test_every_file_inside_is_served(port)


def viewer_folder(tmp_path: Path) -> Path:
    """A subject's outputs with one viewer page."""
    page = tmp_path / "methods" / "toy" / "viewer" / "index.html"
    page.parent.mkdir(parents=True)
    page.write_bytes(PAGE)
    return tmp_path


@pytest.mark.parametrize("bad", ["70000", "-1", "65536"])
def test_a_port_out_of_range_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], bad: str) -> None:
    assert view.main([str(viewer_folder(tmp_path)), "--port", bad]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and bad in err and "--port" in err and "65535" in err


def test_a_busy_port_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        assert view.main([str(viewer_folder(tmp_path)), "--port", str(taken)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"port {taken} is in use" in err and "--port N" in err


def test_help_is_plain_text(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit:
        view.main(["--help"])
    out = capsys.readouterr().out
    assert exit.value.code == 0 and "serve a subject" in out.lower() and "`" not in out


def test_the_server_listens_on_loopback_only(tree: tuple[Path, Path]) -> None:
    server = view.serve(tree[0])
    try:
        assert server.server_address[0] == "127.0.0.1"
    finally:
        server.server_close()


def test_the_links_of_the_tree_do_reach_outside(tree: tuple[Path, Path]) -> None:
    """On the file system the tree's links reach the sentinel: the refusals above are the server's doing."""
    root, _ = tree
    assert (root / "outdir" / "secret.txt").read_bytes() == SENTINEL
    assert (root / "methods/toy/viewer/data/leak.js").read_bytes() == SENTINEL
    assert os.path.realpath(root / "up" / "outside") == os.path.realpath(tree[1])
