"""Contact sheet of the synthetic captures: one row per identity, one column per
camera, all at one contact frame of the training sequence.

    python benchmarks/contact_sheet.py --size 256 --out contact_sheet.png

Prints the generation time per frame (all views) of each identity.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from avatar.synthetic import SyntheticConfig, generate
from avatar.synthetic.capture import SUBJECTS


def contact_sheet(size: int, num_frames: int, sequence: str) -> np.ndarray:
    """(rows * size, cols * size, 3) uint8 RGB sheet at each identity's first contact frame."""
    rows = []
    for subject in SUBJECTS:
        start = time.perf_counter()
        cap = generate(SyntheticConfig(subject, sequence, size, num_frames))
        seconds = time.perf_counter() - start
        frame = int(np.argmax(cap.contact)) if cap.contact.any() else num_frames // 2
        print(
            f"{subject}: {seconds / num_frames:.2f} s per frame ({len(cap.cameras)} views, {size} px), "
            f"showing frame {frame}"
        )
        tiles = []
        for cam in cap.cameras:
            tile = np.ascontiguousarray(cap.frames[cam.camera_id][frame])
            label = f"{cam.camera_id} {cam.split}"
            cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
        rows.append(np.hstack(tiles))
    return np.vstack(rows)


def main() -> None:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=256, help="render resolution per camera (px)")
    parser.add_argument("--frames", type=int, default=6, help="frames in the generated sequence")
    parser.add_argument("--sequence", default="train", choices=("train", "test"))
    parser.add_argument("--out", type=Path, default=Path("contact_sheet.png"))
    args = parser.parse_args()
    sheet = contact_sheet(args.size, args.frames, args.sequence)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
