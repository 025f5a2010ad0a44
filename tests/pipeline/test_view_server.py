"""``interactavatar-view`` serves its folder and nothing else: no file outside it (links followed only inside it,
not even while a folder is swapped for a link), no dot-folder, no listing, no request addressed to another host; bad
ports are one line."""

from __future__ import annotations

import contextlib
import ctypes
import os
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
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
        "methods/toy/viewer/data/up.js": Path("../../../../../outside/secret.txt"),  # out, by a relative target
        "methods/toy/viewer/data/chain.js": Path("leak.js"),  # a link inside to a link that leads out
        "methods/toy/viewer/data/sneak.json": Path("../../../../.cache/sources.json"),  # inside, into a dot-folder
        "methods/toy/viewer/data/page.html": Path("../index.html"),  # inside, relative: may be served
    }
    for name, target in links.items():
        (root / name).symlink_to(target)
    os.mkfifo(root / "methods/toy/viewer/data/pipe.js")  # opened, a FIFO would wait for a writer
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
    assert answer(port, "/methods/toy/viewer/data/page.html") == (200, PAGE)


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
        "/methods/toy/viewer/data/up.js",
        "/methods/toy/viewer/data/chain.js",
        "/methods/toy/viewer/data/sneak.json",
    ],
)
def test_a_link_that_leaves_the_folder_is_refused(port: int, path: str) -> None:
    status, head, body = fetch(port, path)
    assert status in (403, 404) and SENTINEL not in head + body and b"root:" not in body


@pytest.mark.parametrize(
    "path",
    [
        "/../outside/secret.txt",
        "/methods/../../outside/secret.txt",
        "/methods/toy/viewer/data/../../../../../outside/secret.txt",
        "/%2e%2e/outside/secret.txt",
        "/methods/%2E%2E/%2e%2e/outside/secret.txt",
        "/methods%2f..%2f..%2foutside%2fsecret.txt",
        "/methods/..%5c..%5coutside%5csecret.txt",
        "/./methods/toy/viewer/index.html",
    ],
)
def test_dot_dot_is_refused(port: int, path: str) -> None:
    status, head, body = fetch(port, path)
    assert status == 404 and SENTINEL not in head + body and PAGE not in body


def test_a_fifo_is_refused_at_once(port: int) -> None:
    """A FIFO inside the folder is not a regular file: 404 without waiting for a writer."""
    assert answer(port, "/methods/toy/viewer/data/pipe.js")[0] == 404


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


REQUESTS = 1000  # a server that checks a path, then opens it by name, served 18 to 222 of 1000 on 2 busy cores
RENAME_EXCHANGE = 2  # linux/fs.h: swap the two names atomically
AT_FDCWD = -100


def renameat2() -> Callable[[Path, Path], None] | None:
    """A function that swaps two names at once with Linux's ``renameat2(RENAME_EXCHANGE)`` through ctypes, or None
    where the C library lacks it (not Linux, glibc before 2.28)."""
    if sys.platform != "linux":
        return None
    libc = ctypes.CDLL(None, use_errno=True)
    call = getattr(libc, "renameat2", None)
    if call is None:
        return None
    call.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    call.restype = ctypes.c_int

    def exchange(a: Path, b: Path) -> None:
        if call(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE) != 0:
            code = ctypes.get_errno()
            raise OSError(code, os.strerror(code), str(a))

    return exchange


@pytest.fixture
def exchange(tmp_path: Path) -> Callable[[Path, Path], None]:
    """``renameat2(RENAME_EXCHANGE)``, checked to work on the file system of ``tmp_path``; the test is skipped with
    the reason where it does not."""
    swap = renameat2()
    if swap is None:
        pytest.skip("renameat2 is not in this C library (Linux with glibc 2.28 or later has it): no race to run")
    (tmp_path / "probe-a").mkdir()
    (tmp_path / "probe-b").symlink_to("probe-a")
    try:
        swap(tmp_path / "probe-a", tmp_path / "probe-b")
    except OSError as error:
        pytest.skip(f"renameat2(RENAME_EXCHANGE) fails on this file system ({error.strerror}): no race to run")
    return swap


def cpus_apart() -> tuple[set[int], set[int]] | None:
    """This process's CPUs in two groups, the last one alone (the swapper's) and the others (the server's), or None
    with fewer than two: a server and a swapper that share a core swap only while the server waits, never inside
    its requests, and a race that should show would hide for a whole run."""
    cpus = sorted(os.sched_getaffinity(0))
    return (set(cpus[:-1]), {cpus[-1]}) if len(cpus) > 1 else None


@contextlib.contextmanager
def served_by_a_process(root: Path, cpus: set[int] | None) -> Iterator[int]:
    """The port of ``interactavatar-view root`` running in a process of its own (no interpreter lock shared with the
    test), on ``cpus`` where given, stopped on exit."""
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline.view", str(root)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert process.stdout is not None
        address = process.stdout.readline()
        assert address.startswith("http://127.0.0.1:"), f"no address: {address!r}"
        if cpus:
            os.sched_setaffinity(process.pid, cpus)
        yield int(address.split(":")[2].split("/")[0])
    finally:
        process.terminate()
        process.communicate(timeout=10)


def test_a_folder_swapped_for_a_link_never_serves_outside(
    tmp_path: Path, exchange: Callable[[Path, Path], None]
) -> None:
    """A folder inside and a link to a folder outside swap their names in a loop while the server is asked for a file
    of the folder: the check of a path and the open of it by name must not see two different trees (TOCTOU)."""
    root, outside = tmp_path / "served", tmp_path / "outside"
    viewer_folder(root)
    deep = "/".join("abcdefgh")  # the deeper the file below the swapped folder, the wider a check-then-open window
    (root / "data" / deep).mkdir(parents=True)
    (root / "data" / deep / "frame.js").write_bytes(b"inside")
    (outside / deep).mkdir(parents=True)
    (outside / deep / "frame.js").write_bytes(SENTINEL)
    (root / "swap").symlink_to(outside)
    stop, swaps, failures, apart = threading.Event(), [0], list[OSError](), cpus_apart()

    def swap_loop() -> None:
        if apart:
            os.sched_setaffinity(0, apart[1])  # this thread only
        try:
            while not stop.is_set():
                exchange(root / "data", root / "swap")
                swaps[0] += 1
        except OSError as error:
            failures.append(error)

    statuses: list[int] = []
    leaked = 0
    with served_by_a_process(root, apart[0] if apart else None) as port:
        swapper = threading.Thread(target=swap_loop)
        swapper.start()
        try:
            deadline = time.monotonic() + 30
            while len(statuses) < REQUESTS and time.monotonic() < deadline:
                status, head, body = fetch(port, f"/data/{deep}/frame.js")
                statuses.append(status)
                leaked += SENTINEL in head + body
        finally:
            stop.set()
            swapper.join()
    assert swaps[0] > 0 and statuses and not failures, f"the race never ran: {failures}"
    assert leaked == 0, f"{leaked} of {len(statuses)} responses served the file outside the folder"
    assert set(statuses) <= {200, 404} and 200 in statuses  # the folder's own file was served between swaps
