"""Serve a subject's outputs folder on 127.0.0.1 and print the address of each method's browser viewer.

``interactavatar-view <outputs>/<subject>``. The viewer pages (stage ``viewer``: ``methods/<method>/viewer/index.html``)
also open from the file system (``file://``); the server is for browsers or setups that refuse local files, and for
viewing a run on another machine through an SSH tunnel. It listens on the loopback interface only, on a free port
unless ``--port`` names one, until Ctrl-C, and answers only ``GET`` and ``HEAD`` requests addressed to
``127.0.0.1:<port>`` or ``localhost:<port>`` (a page of another site that renames itself to 127.0.0.1 through DNS
rebinding is refused). It serves the regular files inside the folder, links resolved (a link that leads out of the
folder is not followed), except those under a name that starts with ``.`` (``.locks``, ``.cache``, ``.tmp``, ...); a
folder's address serves its ``index.html``, and nothing is listed.
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
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import BinaryIO
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
        file = None if names is None else file_inside(self.root, names)
        if file is None:
            self.send_error(HTTPStatus.NOT_FOUND, explain=NOT_FOUND)
            return None
        if file.is_dir():  # a folder's address without its final slash: its index.html's relative links need it
            self.send_response(HTTPStatus.MOVED_PERMANENTLY)
            self.send_header("Location", path + "/" + ("?" + query if query else ""))
            self.send_header("Content-Length", "0")
            self.end_headers()
            return None
        try:
            opened = file.open("rb")
        except OSError:
            self.send_error(HTTPStatus.NOT_FOUND, explain=NOT_FOUND)
            return None
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", content_type(opened.name))
        self.send_header("Content-Length", str(os.fstat(opened.fileno()).st_size))
        self.end_headers()
        return opened

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


def file_inside(root: Path, names: list[str]) -> Path | None:
    """The regular file ``root/names``, the ``index.html`` of a folder's address (a final ``""``), or the folder
    ``root/names`` names without its final slash, links resolved; None when there is none, or when it resolves
    outside ``root`` or under a name that starts with ``.``."""
    folder_address = not names[-1]
    try:
        real = Path(os.path.realpath(root.joinpath(*names[:-1], names[-1] or "index.html"), strict=True))
        mode = real.stat().st_mode
    except (OSError, ValueError):
        return None
    if not real.is_relative_to(root) or any(name.startswith(".") for name in real.relative_to(root).parts):
        return None
    return real if stat.S_ISREG(mode) or (stat.S_ISDIR(mode) and not folder_address) else None


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
