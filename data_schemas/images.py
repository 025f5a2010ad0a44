"""Image artifacts: OpenEXR for linear float data, PNG for 8-bit frames and label masks.

OpenEXR: float32 or float16 channels, ``(H, W)`` for one channel or ``(H, W, 3|4)``
for a colour layer named ``RGB``/``RGBA``; ZIP compression. openexr 3.5's
bindings silently write wrong data for strided arrays, so every array is made
C-contiguous before it reaches them.

PNG: ``(H, W, 3)`` uint8 sRGB (stored as RGB, not OpenCV's BGR), or ``(H, W)``
uint8 labels/masks.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import OpenEXR

from data_schemas.tables import SchemaError
from data_schemas.writes import write_bytes, write_failed

_EXR_DTYPES = (np.float32, np.float16)


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray]) -> None:
    """Write named float channels (``(H, W)`` or ``(H, W, C)``, all the same H and W)."""
    path = Path(path)
    if not channels:
        raise SchemaError(f"{path}: no channels to write")
    shapes = {a.shape[:2] for a in channels.values()}
    if len(shapes) != 1:
        raise SchemaError(f"{path}: channels disagree on size: {sorted(shapes)}")
    data = {}
    for name, arr in channels.items():
        arr = np.asarray(arr)
        if arr.dtype not in _EXR_DTYPES:
            raise SchemaError(f"{path}: channel '{name}' is {arr.dtype}; EXR channels must be float32 or float16")
        if arr.ndim not in (2, 3) or 0 in arr.shape:
            raise SchemaError(f"{path}: channel '{name}' has shape {arr.shape}; expected (H, W) or (H, W, C)")
        data[name] = np.ascontiguousarray(arr)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with OpenEXR.File(header, data) as f:
            f.write(str(path))
        with OpenEXR.File(str(path), header_only=True):  # reads back the header: cheap
            pass
    except Exception as exc:  # the bindings raise plain RuntimeError/OSError subclasses
        raise write_failed(path, "EXR image", exc) from exc


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """All channels of an EXR file as arrays (``RGB``/``RGBA`` layers as ``(H, W, C)``)."""
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: missing EXR image")
    try:
        with OpenEXR.File(str(path)) as f:
            return {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # the bindings raise plain RuntimeError/OSError subclasses
        raise SchemaError(f"{path}: not a readable OpenEXR file ({exc})") from exc


def to_uint8(image: np.ndarray) -> np.ndarray:
    """An image of floats in [0, 1] (any shape) as uint8: scaled by 255, rounded half up, values outside [0, 1]
    clipped. The one conversion of renders to the PNG and video artifacts."""
    return (image * 255 + 0.5).clip(0, 255).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write ``(H, W)`` or ``(H, W, 3)`` uint8 (RGB order) losslessly."""
    path = Path(path)
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise SchemaError(f"{path}: PNG expects (H, W) or (H, W, 3) uint8, got {image.shape} {image.dtype}")
    bgr = image if image.ndim == 2 else np.ascontiguousarray(image[..., ::-1])
    # Encoded in memory and written here: cv2.imwrite reports success when the disk fills up.
    ok, encoded = cv2.imencode(".png", bgr)
    if not ok:
        raise SchemaError(f"{path}: OpenCV could not encode a {image.shape} PNG")
    write_bytes(path, encoded.tobytes(), "PNG")


def read_png(path: str | Path, channels: int) -> np.ndarray:
    """Read a PNG as ``(H, W)`` uint8 (``channels=1``) or ``(H, W, 3)`` RGB uint8 (``channels=3``)."""
    path = Path(path)
    flag = cv2.IMREAD_GRAYSCALE if channels == 1 else cv2.IMREAD_COLOR
    image = cv2.imread(str(path), flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise SchemaError(f"{path}: missing or unreadable PNG")
    return image if channels == 1 else np.ascontiguousarray(image[..., ::-1])
