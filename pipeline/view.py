"""Serve a subject's outputs folder on 127.0.0.1 and print the address of each method's browser viewer.

``interactavatar-view <outputs>/<subject>``. The viewer pages (stage ``viewer``: ``methods/<method>/viewer/index.html``)
also open from the file system (``file://``); the server is for browsers or setups that refuse local files, and for
viewing a run on another machine through an SSH tunnel. It listens on the loopback interface only, on a free port
unless ``--port`` names one, until Ctrl-C, and answers only ``GET`` and ``HEAD`` requests addressed to
``127.0.0.1:<port>`` or ``localhost:<port>`` (a page of another site that renames itself to 127.0.0.1 through DNS
rebinding is refused). It serves the regular files inside the folder, except those under a name that starts with
``.`` (``.locks``, ``.cache``, ``.tmp``, ...); a folder's address serves its ``index.html``, and nothing is listed. A
request's path is opened one name at a time from the folder's descriptor, never whole by name, and a link is followed
only while its target stays inside the folder: a folder swapped for a link during a request cannot lead out of it.
"""

from __future__ import annotations

import argparse
import errno
import functools
import mimetypes
import os
import shutil
import socket
import socketserver
import stat
import sys
from collections import deque
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import BinaryIO, NamedTuple
from urllib.parse import unquote_to_bytes

VIEWER_PAGE = "viewer/index.html"
HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
    "Cross-Origin-Resource-Policy": "same-origin",  # no other site's page may embed a file of it
}
CONTENT_TYPES = mimetypes.MimeTypes()  # Python's own table: the same types whatever the machine's mime.types say
NOT_FOUND = "Nothing here: open an address that interactavatar-view printed"
MAX_LINKS = 40  # links one request may pass through, as Linux's own limit: a loop of links is refused
FOLDER_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
ENTRY_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK  # O_NONBLOCK: a FIFO does not hang a thread


class FolderHandler(BaseHTTPRequestHandler):
    """``GET`` and ``HEAD`` of the regular files inside ``root``, for requests addressed to this server; no log line
    per request."""

    def __init__(
        self, request: socket.socket, client_address: tuple[str, int], server: socketserver.BaseServer, *, root: Path
    ) -> None:
        self.root = root
        super().__init__(request, client_address, server)  # handles the request

    def do_GET(self) -> None:
        file = self.open_requested()
        if file is not None:
            with file:
                try:
                    shutil.copyfileobj(file, self.wfile)
                except ConnectionError:  # the browser cancelled the load (a new frame asked for): nothing to report
                    self.close_connection = True

    def do_HEAD(self) -> None:
        file = self.open_requested()
        if file is not None:
            file.close()

    def open_requested(self) -> BinaryIO | None:
        """The requested file, open, after its status and headers are sent; None when an error or a redirect was
        sent instead."""
        port = self.connection.getsockname()[1]  # the port the server listens on
        if self.headers.get_all("Host") not in ([f"127.0.0.1:{port}"], [f"localhost:{port}"]):
            self.send_error(
                HTTPStatus.MISDIRECTED_REQUEST,
                explain=f"This server answers only 127.0.0.1:{port} and localhost:{port}",
            )
            return None
        path, _, query = self.path.partition("#")[0].partition("?")
        names = request_names(path)
        found = None if names is None else file_inside(self.root, names)
        if found is None:
            self.send_error(HTTPStatus.NOT_FOUND, explain=NOT_FOUND)
            return None
        if found.file is None:  # a folder's address without its final slash: its index.html's relative links need it
            self.send_response(HTTPStatus.MOVED_PERMANENTLY)
            self.send_header("Location", path + "/" + ("?" + query if query else ""))
            self.send_header("Content-Length", "0")
            self.end_headers()
            return None
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", content_type(found.name))
        self.send_header("Content-Length", str(found.size))
        self.end_headers()
        return found.file

    def end_headers(self) -> None:
        for name, value in HEADERS.items():
            self.send_header(name, value)
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:
        pass


def request_names(path: str) -> list[str] | None:
    """The names of a request path's components, percent-decoded, with a final ``""`` for a folder's address; None
    when the path is not absolute or not UTF-8, holds a backslash or a NUL, or a name is empty or starts with ``.``
    (``.``, ``..``, ``.cache``)."""
    try:
        decoded = unquote_to_bytes(path.encode("latin-1")).decode("utf-8")  # the request line was read as Latin-1
    except UnicodeError:
        return None
    if not decoded.startswith("/") or "\\" in decoded or "\x00" in decoded:
        return None
    names = decoded[1:].split("/")
    return None if any(name.startswith(".") for name in names) or not all(names[:-1]) else names


class Found(NamedTuple):
    """What a request names inside the served folder."""

    file: BinaryIO | None  # the regular file, open; None for a folder
    name: str  # its own name in its folder (a link's target's, for a link): what its content type follows
    size: int


def file_inside(root: Path, names: list[str]) -> Found | None:
    """The regular file ``root/names``, the ``index.html`` of a folder's address (a final ``""``), or the folder
    ``root/names`` names without its final slash, opened inside ``root`` (see ``open_inside``); None when there is
    none, or when it lies outside ``root``, under a name that starts with ``.``, or is something else (a FIFO, a
    device)."""
    folder_address = not names[-1]
    opened = open_inside(root, [*names[:-1], names[-1] or "index.html"])
    if opened is None:
        return None
    descriptor, name = opened
    mode, size = stat_of(descriptor)
    if stat.S_ISREG(mode):
        return Found(os.fdopen(descriptor, "rb"), name, size)
    os.close(descriptor)
    return Found(None, name, 0) if stat.S_ISDIR(mode) and not folder_address else None


def stat_of(descriptor: int) -> tuple[int, int]:
    """The mode and size of an open ``descriptor``, what was opened, never what its name leads to now; mode 0 when
    it cannot be read."""
    try:
        status = os.fstat(descriptor)
    except OSError:
        return 0, 0
    return status.st_mode, status.st_size


def open_inside(root: Path, names: list[str]) -> tuple[int, str] | None:
    """A descriptor of what ``root/names`` leads to, and that entry's name in its folder; None when it leaves ``root``,
    passes a name that starts with ``.``, or does not exist.

    The path is never handed to the kernel whole: each name is opened from the descriptor of the folder before it,
    without following a link (``O_NOFOLLOW``), so that a folder swapped for a link between a check and an open cannot
    lead elsewhere. A link is read and its target walked the same way from the folders already opened (its ``..``
    steps back through them, never above ``root``); an absolute target must name a place under ``root``'s own path.
    """
    try:
        folders = [os.open(root, FOLDER_FLAGS)]
    except OSError:
        return None
    try:
        return walk(root, folders, deque(names))
    except OSError:
        return None
    finally:
        for folder in folders:
            os.close(folder)


def walk(root: Path, folders: list[int], pending: deque[str]) -> tuple[int, str] | None:
    """Open the names ``pending`` one by one from the folder ``folders[-1]``, each folder onto ``folders``; the
    descriptor of the last entry (a new one) and its name, or None where the walk is refused (see ``open_inside``).
    OSError when an entry is missing or changed between its look and its open."""
    name, links = "", 0
    while pending:
        name = pending.popleft()
        if name in ("", ".", ".."):  # only a link's target spells these: the request's names never do
            if name == ".." and len(folders) == 1:
                return None
            if name == "..":
                os.close(folders.pop())
            continue
        if name.startswith("."):
            return None
        mode = os.stat(name, dir_fd=folders[-1], follow_symlinks=False).st_mode
        if not (stat.S_ISLNK(mode) or stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
            return None  # a FIFO, a socket, a device: never opened
        if stat.S_ISLNK(mode):
            links += 1
            target = link_names(root, os.readlink(name, dir_fd=folders[-1]))
            if target is None or links > MAX_LINKS:
                return None
            from_root, names = target
            while from_root and len(folders) > 1:
                os.close(folders.pop())
            pending.extendleft(reversed(names))
        elif not pending:
            return os.open(name, ENTRY_FLAGS, dir_fd=folders[-1]), name
        else:
            folders.append(os.open(name, FOLDER_FLAGS, dir_fd=folders[-1]))
    return os.dup(folders[-1]), name


def link_names(root: Path, target: str) -> tuple[bool, list[str]] | None:
    """The names a link's ``target`` walks through, and whether it walks them from ``root`` (an absolute target)
    rather than from the link's folder; None for an absolute target that does not spell a place under ``root``'s own
    path."""
    if not target.startswith("/"):
        return False, target.split("/")
    prefix = root.as_posix().rstrip("/") + "/"
    if target != prefix[:-1] and not target.startswith(prefix):
        return None
    return True, target[len(prefix) :].split("/")


def content_type(name: str) -> str:
    """The media type of a file named ``name`` (Python's own table, not the machine's ``mime.types``)."""
    kind, encoding = CONTENT_TYPES.guess_type(name)
    return kind if kind and not encoding else "application/octet-stream"


def viewer_pages(root: Path) -> list[Path]:
    """The viewer pages under a subject's outputs ``root`` (``methods/*/viewer/index.html``), or ``root``'s own page
    when it is a viewer folder."""
    if (root / "index.html").is_file() and (root / "data" / "manifest.js").is_file():
        return [root / "index.html"]
    return sorted(root.glob(f"methods/*/{VIEWER_PAGE}"))


def serve(root: Path, port: int = 0) -> ThreadingHTTPServer:
    """A server of ``root`` on 127.0.0.1 (``port`` 0: a free one), not yet started; OSError when it cannot listen
    there."""
    return ThreadingHTTPServer(("127.0.0.1", port), functools.partial(FolderHandler, root=root.resolve()))


def listen_problem(port: int, error: OSError) -> str:
    """One line that says why the server cannot listen on ``port`` and what to do."""
    fix = "choose another with --port N or leave it out for a free one"
    if error.errno == errno.EADDRINUSE:
        return f"port {port} is in use; {fix}"
    return f"cannot listen on 127.0.0.1:{port} ({error.strerror or error}); {fix}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="interactavatar-view", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("outputs", type=Path, help="a subject's outputs folder (<paths.outputs>/<subject>)")
    parser.add_argument("--port", type=int, default=0, help="the port to listen on (default: a free one)")
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        print(
            f"interactavatar-view: --port {args.port} is not a port; choose one from 1 to 65535 with --port N or "
            f"leave it out for a free one",
            file=sys.stderr,
        )
        return 2
    root = args.outputs.resolve()
    pages = viewer_pages(root) if root.is_dir() else []
    if not pages:
        print(
            f"interactavatar-view: {root} has no viewer (methods/<method>/{VIEWER_PAGE}); run the pipeline's viewer "
            f"stage first: interactavatar run.only=viewer",
            file=sys.stderr,
        )
        return 2
    try:
        server = serve(root, args.port)
    except OSError as error:
        print(f"interactavatar-view: {listen_problem(args.port, error)}", file=sys.stderr)
        return 2
    port = server.server_address[1]
    for page in pages:
        print(f"http://127.0.0.1:{port}/{page.relative_to(root).as_posix()}")
    print("Ctrl-C stops the server.", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
