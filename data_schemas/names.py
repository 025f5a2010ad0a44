"""Names that become path components: subjects, methods, sequences and camera ids.

A capture's names (its sequence folders, its camera ids from video names, image folders or a calibration) and
the config's (``subject``, ``method``) name folders and files of every artifact: ``frames/<sequence>/<camera>/``,
``reenact/videos/<camera>.mp4``, ``methods/<method>/``. One rule per kind, checked once where a name enters
(the config check before any stage runs, a capture adapter before it writes, every reader and writer of
``cameras.parquet`` and ``capture.json``), so no name can leave its folder (``..``, ``a/b``), hide (``.x``),
stand for a device on another system (``CON``, ``NUL``) or share a path with another artifact (a camera named
``orbit`` beside reenact's orbit view).
"""

from __future__ import annotations

import re

from data_schemas.tables import SchemaError

#: The rule of subject, method and sequence names, in words (for messages).
FOLDER_NAME_RULE = "letters, digits, '-' or '_', starting with a letter or digit, at most 64 characters"
#: The rule of camera ids, in words: as folder names, and '.' inside (calibrations number cameras '22.1').
CAMERA_ID_RULE = "letters, digits, '.', '-' or '_', starting with a letter or digit, at most 64 characters"
_FOLDER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")
_CAMERA_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
#: Device names Windows reserves in every folder, with any extension (a capture may live on a shared drive).
_DEVICE_NAMES = frozenset(
    ("con", "prn", "aux", "nul", *(f"com{i}" for i in range(1, 10)), *(f"lpt{i}" for i in range(1, 10)))
)
#: Camera ids the reenactment's own files take (stage reenact: ``videos/orbit.mp4`` is the orbit view,
#: ``videos/<camera>_gt.mp4`` and ``<camera>_vs_gt.mp4`` a camera's ground truth), with why.
RESERVED_CAMERA_IDS = {"orbit": "the reenactment's orbit view (reenact/videos/orbit.mp4)"}
RESERVED_CAMERA_SUFFIXES = {
    "_gt": "a camera's ground-truth video in the reenactment (reenact/videos/<camera>_gt.mp4)",
    "_vs_gt": "a camera's side-by-side video in the reenactment (reenact/videos/<camera>_vs_gt.mp4)",
}


def folder_name_problem(value: object) -> str | None:
    """Why ``value`` cannot name a subject, method or sequence folder (the caller puts the name and where it
    comes from before it), or ``None`` when it can."""
    if not isinstance(value, str) or not _FOLDER_NAME.fullmatch(value):
        return f"use {FOLDER_NAME_RULE}"
    return _device_problem(value)


def camera_id_problem(value: object) -> str | None:
    """Why ``value`` cannot be a camera id (the caller puts the id and where it comes from before it), or
    ``None`` when it can."""
    if not isinstance(value, str) or not _CAMERA_ID.fullmatch(value):
        return f"use {CAMERA_ID_RULE}"
    if value.lower() in RESERVED_CAMERA_IDS:
        return f"reserved for {RESERVED_CAMERA_IDS[value.lower()]}; rename the camera"
    suffix = next((s for s in RESERVED_CAMERA_SUFFIXES if value.lower().endswith(s)), None)
    if suffix is not None:
        return f"a name ending in '{suffix}' is reserved for {RESERVED_CAMERA_SUFFIXES[suffix]}; rename the camera"
    return _device_problem(value)


def check_camera_id(value: object, where: str) -> None:
    """Raise :class:`SchemaError` ``"<where>: camera id '<value>': <why>"`` when ``value`` cannot be a camera id."""
    problem = camera_id_problem(value)
    if problem is not None:
        raise SchemaError(f"{where}: camera id {value!r}: {problem}")


def check_sequence_name(value: object, where: str) -> None:
    """Raise :class:`SchemaError` ``"<where>: sequence '<value>': <why>"`` when ``value`` cannot name a
    sequence (its folder in every stage that keeps one per sequence)."""
    problem = folder_name_problem(value)
    if problem is not None:
        raise SchemaError(f"{where}: sequence {value!r}: {problem}")


def _device_problem(value: str) -> str | None:
    if value.split(".", 1)[0].lower() in _DEVICE_NAMES:
        return "a device name reserved on Windows file systems; rename it"
    return None
