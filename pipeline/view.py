"""``interactavatar-view <outputs>/<subject>``: serve a subject's outputs on 127.0.0.1 and print the address of each
method's browser viewer (stage ``viewer``: ``methods/<method>/viewer/index.html``).

The pages also open from the file system (``file://``); the server is for browsers or setups that refuse local files,
and for viewing a run on another machine through an SSH tunnel. It serves only that folder, only on the loopback
interface, on a free port unless ``--port`` names one, until Ctrl-C.
"""

from __future__ import annotations

import argparse
import functools
import sys
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

VIEWER_PAGE = "viewer/index.html"


class QuietHandler(SimpleHTTPRequestHandler):
    """Static files, without a log line per request."""

    def log_message(self, format: str, *args: object) -> None:
        pass


def viewer_pages(root: Path) -> list[Path]:
    """The viewer pages under a subject's outputs ``root`` (``methods/*/viewer/index.html``), or ``root``'s own page
    when it is a viewer folder."""
    if (root / "index.html").is_file() and (root / "data" / "manifest.js").is_file():
        return [root / "index.html"]
    return sorted(root.glob(f"methods/*/{VIEWER_PAGE}"))


def serve(root: Path, port: int = 0) -> ThreadingHTTPServer:
    """A server of ``root`` on 127.0.0.1 (``port`` 0: a free one), not yet started."""
    return ThreadingHTTPServer(("127.0.0.1", port), functools.partial(QuietHandler, directory=str(root)))


def main(argv: list[str] | None = None) -> int:
    summary = __doc__.splitlines()[0] if __doc__ else None
    parser = argparse.ArgumentParser(prog="interactavatar-view", description=summary)
    parser.add_argument("outputs", type=Path, help="a subject's outputs folder (<paths.outputs>/<subject>)")
    parser.add_argument("--port", type=int, default=0, help="the port to listen on (default: a free one)")
    args = parser.parse_args(argv)
    root = args.outputs.resolve()
    pages = viewer_pages(root) if root.is_dir() else []
    if not pages:
        print(
            f"interactavatar-view: {root} has no viewer (methods/<method>/{VIEWER_PAGE}); run the pipeline's viewer "
            f"stage first: interactavatar run.only=viewer",
            file=sys.stderr,
        )
        return 2
    server = serve(root, args.port)
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
