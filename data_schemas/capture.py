"""The ``capture`` artifact: a multi-view recording, as a studio (or the generator) delivers it.

Layout (``<capture>`` is a stage directory, or a subject folder of a folder dataset)::

    cameras.parquet                      calibration, one row per camera
    capture.json                         index: sequences, frame counts, frame rate, what exists
    <sequence>/videos/<camera_id>.mp4    one video per camera
    <sequence>/masks/<camera_id>/<frame:06d>.png   optional part labels (0 bg, 1 face, 2 hand)
    <sequence>/gt/params.parquet         optional ground truth (synthetic captures)
    <sequence>/gt/keypoints.parquet
    <sequence>/gt/deform.parquet
    <sequence>/provided/keypoints.parquet   optional, shipped with the dataset (DECAF): 2D keypoints
    <sequence>/provided/params.parquet      FLAME/MANO parameters (the dataset's own multi-view fit)
    <sequence>/provided/deform.parquet      per-vertex face offsets (data_schemas.deform.DEFORM)
    <sequence>/provided/contacts.parquet    per-vertex contacts (data_schemas.deform.CONTACTS)

Sequences are named ``train`` and ``test`` (held-out motion). ``SequenceInfo.provided``
lists the ``provided/`` tables a sequence has; ``SequenceInfo.notes`` says what the
dataset ships that was not imported, and why.
"""

from __future__ import annotations

import fcntl
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

from data_schemas.names import check_sequence_name
from data_schemas.tables import SchemaError
from data_schemas.writes import write_failed, write_json

CAPTURE_INDEX = "capture.json"
CAPTURE_VERSION = 2
MASK_LABELS = {"background": 0, "face": 1, "hand": 2}
PROVIDED_TABLES = ("keypoints", "params", "deform", "contacts")


@dataclass(frozen=True)
class SequenceInfo:
    num_frames: int
    frame_rate: float
    width: int
    height: int
    has_masks: bool
    has_ground_truth: bool
    provided: tuple[str, ...] = ()  # which PROVIDED_TABLES exist under <sequence>/provided/
    notes: tuple[str, ...] = ()  # what the dataset ships that was not imported, and why

    def has_provided(self, name: str) -> bool:
        """Whether ``<sequence>/provided/<name>.parquet`` exists (``name`` in PROVIDED_TABLES)."""
        return name in self.provided


@dataclass(frozen=True)
class CaptureIndex:
    subject: str
    dataset: str
    sequences: dict[str, SequenceInfo]

    def write(self, root: Path) -> None:
        for name in self.sequences:
            check_sequence_name(name, str(root / CAPTURE_INDEX))
        body = {
            "schema_version": CAPTURE_VERSION,
            "subject": self.subject,
            "dataset": self.dataset,
            "sequences": {k: asdict(v) for k, v in self.sequences.items()},
        }
        write_json(root / CAPTURE_INDEX, body, "capture index")

    @classmethod
    def read(cls, root: Path) -> CaptureIndex:
        path = root / CAPTURE_INDEX
        try:
            body = json.loads(path.read_text())
            if body.get("schema_version") != CAPTURE_VERSION:
                raise SchemaError(f"{path}: schema_version {body.get('schema_version')} != {CAPTURE_VERSION}")
            sequences = {
                k: SequenceInfo(**{**v, "provided": tuple(v.get("provided", ())), "notes": tuple(v.get("notes", ()))})
                for k, v in body["sequences"].items()
            }
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise SchemaError(f"{path}: missing or malformed capture index ({exc})") from exc
        for name in sequences:
            check_sequence_name(name, str(path))
        return cls(subject=body["subject"], dataset=body["dataset"], sequences=sequences)


def cross_sequence(performer: str) -> str:
    """Name of the synthetic sequence in which the subject performs ``performer``'s held-out motion (the
    ground truth of cross-actor reenactment driven by ``performer``)."""
    return f"cross_{performer}"


def video_path(root: Path, sequence: str, camera_id: str) -> Path:
    return root / sequence / "videos" / f"{camera_id}.mp4"


def mask_path(root: Path, sequence: str, camera_id: str, frame: int) -> Path:
    return root / sequence / "masks" / camera_id / f"{frame:06d}.png"


def gt_path(root: Path, sequence: str, name: str) -> Path:
    """``name`` is one of ``params``, ``keypoints``, ``deform``."""
    return root / sequence / "gt" / f"{name}.parquet"


def provided_path(root: Path, sequence: str, name: str) -> Path:
    """``name`` is one of :data:`PROVIDED_TABLES`."""
    return root / sequence / "provided" / f"{name}.parquet"


_FICLONE = 0x40049409  # Linux ioctl: share the source's blocks copy-on-write (btrfs, XFS, bcachefs)


def copy_into_capture(src: Path, dst: Path) -> None:
    """Bring a user's file into a capture as an independent copy: a copy-on-write clone where the file system
    has one, else a byte copy. Never a hard link: editing the user's file must not change a published artifact."""
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(src, "rb") as fin, open(dst, "wb") as fout:
            try:
                fcntl.ioctl(fout.fileno(), _FICLONE, fin.fileno())
                cloned = True
            except OSError:
                cloned = False
        if not cloned:
            shutil.copyfile(src, dst)
        shutil.copystat(src, dst)
    except OSError as exc:
        raise write_failed(dst, f"copy of {src}", exc) from exc
