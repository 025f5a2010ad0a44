"""The report counts contact frames from ground truth or from the contacts a dataset ships, and says which
(issue 36, item 14: a DECAF-layout capture with contacts said "No contact ground truth")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from data_schemas.capture import CaptureIndex, SequenceInfo, provided_path
from data_schemas.deform import CONTACTS
from data_schemas.tables import write_table
from reporting.capture import contact_summary


def test_shipped_contacts_are_counted_and_named(tmp_path: Path) -> None:
    shipped = SequenceInfo(
        num_frames=4,
        frame_rate=30.0,
        width=8,
        height=8,
        has_masks=False,
        has_ground_truth=False,
        provided=("contacts",),
    )
    bare = SequenceInfo(num_frames=4, frame_rate=30.0, width=8, height=8, has_masks=False, has_ground_truth=False)
    index = CaptureIndex(subject="s", dataset="decaf", sequences={"train": shipped, "test": bare})
    index.write(tmp_path)
    contact = np.array([True, False, True, True])
    write_table(
        provided_path(tmp_path, "train", "contacts"),
        CONTACTS,
        {
            "frame": np.arange(4, dtype=np.int32),
            "contact": contact,
            "face": [np.zeros(3, np.float32)] * 4,
            "hand": [np.zeros(3, np.float32)] * 4,
        },
    )
    text = contact_summary(tmp_path, index)
    assert "train: 3 of 4 frames with contact (shipped with the dataset)" in text
    assert "test" not in text  # no labels: not counted as zero
    empty = CaptureIndex(subject="s", dataset="folder", sequences={"test": bare})
    assert "No contact labels in this capture" in contact_summary(tmp_path, empty)
