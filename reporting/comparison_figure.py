"""The paper's image rows: each method's render of the same frame and view beside the truth, cropped to the hand or
to the interaction."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from avatar.preprocess.crops import label_box, overlap_box
from data_schemas.capture import MASK_LABELS
from data_schemas.frames import crop_mask_path, rgb_path
from data_schemas.images import read_png
from data_schemas.metrics import showcase_path
from reporting.method_runs import MethodRun


def image_row_figure(
    runs: list[MethodRun], frames_dir: Path, split: str, sequence: str, crop: str, px: int
) -> np.ndarray | None:
    """Rows of showcase frames, columns ground truth then each method that rendered ``split``, cropped to the
    hand box or the hand-face overlap box of the ground truth's labels; ``None`` when no frame has that box."""
    runs = [r for r in runs if (r.evaluate_dir / "renders" / split).is_dir()]
    if not runs:
        return None
    render_dir = runs[0].evaluate_dir / "renders" / split
    rows = []
    for path in sorted(render_dir.glob("*.png")):
        frame_text, camera_id = path.stem.split("_", 1)
        frame = int(frame_text)
        labels = read_png(crop_mask_path(frames_dir, sequence, camera_id, frame), 1)
        hand = label_box(labels, MASK_LABELS["hand"])
        box = hand if crop == "hand" else overlap_box(hand, label_box(labels, MASK_LABELS["face"]))
        if box is None:
            continue
        images = [read_png(rgb_path(frames_dir, sequence, camera_id, frame), 3)]
        images += [read_png(showcase_path(r.evaluate_dir, split, frame, camera_id), 3) for r in runs]
        rows.append(np.concatenate([crop_box(image, box, px) for image in images], axis=1))
    if not rows:
        return None
    header = np.full((18, rows[0].shape[1], 3), 255, np.uint8)
    for i, name in enumerate(["ground truth"] + [r.label for r in runs]):
        cv2.putText(header, name[:16], (i * px + 2, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([header, *rows], axis=0)


def crop_box(image: np.ndarray, box: np.ndarray, px: int) -> np.ndarray:
    """The square around ``box`` (x0, y0, x1, y1) of ``image`` (S, S, 3), resized to (px, px, 3)."""
    size = image.shape[0]
    x0, y0, x1, y1 = box
    side = max(x1 - x0, y1 - y0, 8.0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    lo_x = int(np.clip(round(cx - side / 2), 0, max(size - side, 0)))
    lo_y = int(np.clip(round(cy - side / 2), 0, max(size - side, 0)))
    side_px = int(min(round(side), size))
    patch = image[lo_y : lo_y + side_px, lo_x : lo_x + side_px]
    return cv2.resize(patch, (px, px), interpolation=cv2.INTER_AREA if side_px > px else cv2.INTER_NEAREST)
