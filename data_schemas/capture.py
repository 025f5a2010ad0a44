"""The ``capture`` artifact: a multi-view recording, as a studio (or the generator) delivers it.

Layout (``<capture>`` is a stage directory, or a subject folder of a folder dataset)::

    cameras.parquet                      calibration, one row per camera
    capture.json                         index: sequences, frame counts, frame rate, what exists
    <sequence>/videos/<camera_id>.mp4    one video per camera
    <sequence>/masks/<camera_id>/<frame:06d>.png   optional part labels (0 bg, 1 face, 2 hand)
    <sequence>/gt/params.parquet         optional ground truth (synthetic captures)
    <sequence>/gt/keypoints.parquet
    <sequence>/gt/deform.parquet

Sequences are named ``train`` and ``test`` (held-out motion).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from data_schemas.tables import SchemaError

CAPTURE_INDEX = "capture.json"
CAPTURE_VERSION = 1
MASK_LABELS = {"background": 0, "face": 1, "hand": 2}


@dataclass(frozen=True)
class SequenceInfo:
    num_frames: int
    frame_rate: float
    width: int
    height: int
    has_masks: bool
    has_ground_truth: bool


@dataclass(frozen=True)
class CaptureIndex:
    subject: str
    dataset: str
    sequences: dict[str, SequenceInfo]

    def write(self, root: Path) -> None:
        body = {"schema_version": CAPTURE_VERSION, "subject": self.subject, "dataset": self.dataset,
                "sequences": {k: asdict(v) for k, v in self.sequences.items()}}
        (root / CAPTURE_INDEX).write_text(json.dumps(body, indent=2, sort_keys=True))

    @classmethod
    def read(cls, root: Path) -> CaptureIndex:
        path = root / CAPTURE_INDEX
        try:
            body = json.loads(path.read_text())
            if body.get("schema_version") != CAPTURE_VERSION:
                raise SchemaError(f"{path}: schema_version {body.get('schema_version')} != {CAPTURE_VERSION}")
            sequences = {k: SequenceInfo(**v) for k, v in body["sequences"].items()}
            return cls(subject=body["subject"], dataset=body["dataset"], sequences=sequences)
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise SchemaError(f"{path}: missing or malformed capture index ({exc})") from exc


def video_path(root: Path, sequence: str, camera_id: str) -> Path:
    return root / sequence / "videos" / f"{camera_id}.mp4"


def mask_path(root: Path, sequence: str, camera_id: str, frame: int) -> Path:
    return root / sequence / "masks" / camera_id / f"{frame:06d}.png"


def gt_path(root: Path, sequence: str, name: str) -> Path:
    """``name`` is one of ``params``, ``keypoints``, ``deform``."""
    return root / sequence / "gt" / f"{name}.parquet"
