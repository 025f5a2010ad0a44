"""The report page's building blocks: the page, tables, embedded PNG images and figures, the contact sheet."""

from __future__ import annotations

import base64
import io
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from data_schemas import web_escape as esc
from data_schemas.frames import rgb_path
from data_schemas.images import read_png


def page(sections: list[str]) -> str:
    """The report's HTML document around its ``sections`` (HTML, every name in them escaped)."""
    return (
        "<!doctype html><meta charset='utf-8'><title>InteractAvatar report</title>"
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}"
        "img,video{max-width:100%;height:auto}figure{margin:1em 0}</style>\n" + "\n".join(sections)
    )


def figure_png(fig) -> str:  # a matplotlib Figure
    """Base64 PNG of a matplotlib figure, closed afterwards."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def pyplot():  # the matplotlib.pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_image(alt: str, png_base64: str) -> str:
    """An ``<img>`` of a base64 PNG (its alphabet needs no escaping) described by ``alt``."""
    return f"<img alt='{esc.text(alt)}' src='data:image/png;base64,{png_base64}'>"


def base64_file(path: Path) -> str:
    """Base64 of a file (a PNG or a video) for a data URI."""
    return base64.b64encode(path.read_bytes()).decode()


#: the contact sheet's rows hold at most this many tiles, and are at most this many pixels wide (a page of 1280
#: CSS pixels less its margins; the page's CSS shrinks any wider image to fit as well)
SHEET_COLUMNS, SHEET_MAX_PX = 4, 1200


def contact_sheet(frames_dir: Path, seq: str, camera_ids: list[str], frame: int, px: int) -> str:
    """Base64 PNG of every camera's crop of ``frame`` of ``seq``, ``px`` square each, in rows (:func:`tile_grid`)."""
    tiles = [
        cv2.resize(read_png(rgb_path(frames_dir, seq, cid, frame), 3), (px, px), interpolation=cv2.INTER_AREA)
        for cid in camera_ids
    ]
    return image_png(tile_grid(tiles))


def tile_grid(
    tiles: Sequence[np.ndarray], columns: int = SHEET_COLUMNS, max_px: int = SHEET_MAX_PX, gap: int = 4
) -> np.ndarray:
    """(H, W, 3) uint8: ``tiles`` (each (h, w, 3), one size) row by row on white, ``gap`` pixels apart, as many per
    row as fit ``max_px`` up to ``columns`` (at least one)."""
    h, w = tiles[0].shape[:2]
    per_row = max(1, min(columns, len(tiles), (max_px + gap) // (w + gap)))
    rows = math.ceil(len(tiles) / per_row)
    grid = np.full((rows * (h + gap) - gap, per_row * (w + gap) - gap, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, per_row)
        grid[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = tile
    return grid


def image_png(image: np.ndarray) -> str:
    """Base64 PNG of an (H, W, 3) uint8 RGB image."""
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    assert ok
    return base64.b64encode(png.tobytes()).decode()


def html_table(headers: tuple[str, ...], rows: list[tuple]) -> str:
    """An HTML table of ``headers`` and ``rows`` (any values: each cell is ``str(value)``, escaped)."""
    head = "".join(f"<th>{esc.text(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{esc.text(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"
