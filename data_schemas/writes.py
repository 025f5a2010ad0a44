"""Checked writes: a writer that fails (a full disk, a read-only or vanished directory) raises one error
that names the file and the operating system's reason, and leaves no partial file behind.

Some encoders report success although their output is unusable (OpenCV's video writer on a full disk
closes a file without its index), so writers also read back what they wrote, as cheaply as possible:
the byte count, a Parquet footer, a video's frame count and first frame.
"""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path

# Below this much free space a failed write is put down to a full disk.
NEARLY_FULL_BYTES = 1 << 20


class WriteError(OSError):
    """An artifact could not be written; the message names the file, the reason and the fix."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.errno = code

    def __str__(self) -> str:
        return str(self.args[0])


def _free_bytes(path: Path) -> int | None:
    for folder in (path, *path.parents):
        if folder.is_dir():
            try:
                return shutil.disk_usage(folder).free
            except OSError:
                return None
    return None


def write_failed(path: str | Path, what: str, cause: BaseException | None = None) -> WriteError:
    """The error for a failed write of ``path`` (``what``: "PNG", "video", ...), after removing the partial
    file. The reason is the OS error where there is one; a failure on a nearly full disk is called one."""
    path = Path(path)
    code = getattr(cause, "errno", None) if isinstance(cause, OSError) else None
    if code:
        reason = getattr(cause, "strerror", None) or str(cause)
    else:
        reason = str(cause).strip().splitlines()[0] if cause is not None and str(cause).strip() else ""
    reason = reason.rstrip(". ")
    free = _free_bytes(path.parent)
    full = (
        code == errno.ENOSPC
        or "no space left on device" in reason.lower()
        or (free is not None and free < NEARLY_FULL_BYTES)
    )
    if full:
        code = errno.ENOSPC
        if "no space left on device" not in reason.lower():
            reason = f"{reason}; " if reason else ""
            reason += "no space left on device" + (f" ({free} bytes free)" if free is not None else "")
        reason += "; free space there or point paths.outputs at a larger disk"
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass
    return WriteError(f"{path}: could not write the {what}: {reason or 'it does not read back as written'}", code)


def write_bytes(path: str | Path, data: bytes, what: str) -> None:
    """Write ``data`` to ``path`` (creating its folder); raise :class:`WriteError` if that fails or the file
    on disk does not have ``len(data)`` bytes."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:
            f.write(data)
        size = path.stat().st_size
    except OSError as exc:
        raise write_failed(path, what, exc) from exc
    if size != len(data):
        raise write_failed(path, what, OSError(f"{size} of {len(data)} bytes on disk"))


def write_json(path: str | Path, obj: object, what: str) -> None:
    """``obj`` as indented JSON with sorted keys (the same bytes for the same content), checked like
    :func:`write_bytes`."""
    write_bytes(path, json.dumps(obj, indent=2, sort_keys=True).encode(), what)
