"""Cross-actor motion transfer against the generator's placement (issue 35, part 3): geometry only, no training.

For each subject pair at ``quality=draft`` (12 frames of the held-out motion): the driver's ground-truth parameters
of its ``test`` sequence are transferred onto the target (identity from the target's ``train`` sequence) with
``reenact.placement=scaled`` (the hand-to-head transform scaled by the head sizes) and ``contact`` (the touches
kept on the same surface points), and compared with the ground truth of the target's ``cross_<driver>`` sequence:
the same script performed by the target, which the generator places against the target's own face. Prints the
mean hand vertex error (mm) over all frames, the contact frames and the others, per frame, the touching points
kept and their residual, and writes ``benchmarks/results/bench_transfer.{json,md}`` (commit, machine).

Usage: python benchmarks/bench_transfer.py [--results DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from avatar.posing import posed_keypoints  # noqa: E402
from avatar.reenact import PLACEMENTS, transfer_motion  # noqa: E402
from avatar.reenact.contact import TOUCH_M, surface_twins  # noqa: E402
from avatar.synthetic import SyntheticConfig, generate  # noqa: E402
from avatar.templates import procedural_hand, procedural_head  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from pipeline.summary import format_table  # noqa: E402

PAIRS = (("synth_a", "synth_b"), ("synth_b", "synth_a"))
#: quality=draft frames of the held-out motion (conf/quality/draft.yaml)
FRAMES = 12


def _params(subject: str, sequence: str, frames: int, performer: str | None = None) -> tuple[dict, np.ndarray]:
    """Ground-truth parameters and contact flags (T,) of one sequence (rendered at a token size: only the motion
    is used)."""
    cap = generate(
        SyntheticConfig(
            subject, sequence, image_size=16, num_frames=frames, supersample=1, num_cameras=2, performer=performer
        )
    )
    return cap.params, cap.contact


def touches_kept(driver: dict, transferred: dict, head, hand) -> tuple[int, int]:
    """(driver hand vertices touching the driver's face, of those touching the target's face after the transfer),
    summed over the frames: the same count for any placement."""
    faces = np.asarray(head.faces)
    d, o = posed_keypoints(driver, head, hand), posed_keypoints(transferred, head, hand)
    touching = kept = 0
    for t in range(len(d["hand_vertices"])):
        near = surface_twins(d["hand_vertices"][t], d["face_vertices"][t], faces).local[:, 2] < TOUCH_M
        if near.any():
            touching += int(near.sum())
            kept += int(
                (surface_twins(o["hand_vertices"][t][near], o["face_vertices"][t], faces).local[:, 2] < TOUCH_M).sum()
            )
    return touching, kept


def measure() -> list[dict]:
    """Per pair and placement: the hand vertex errors (mm) per frame and the transfer's report."""
    head, hand = procedural_head(), procedural_hand()
    rows = []
    for target, driver in PAIRS:
        driver_params, _ = _params(driver, "test", FRAMES)
        truth, contact = _params(target, "test", FRAMES, performer=driver)
        identity, _ = _params(target, "train", 2)
        truth_hand = posed_keypoints(truth, head, hand)["hand_vertices"]
        for placement in PLACEMENTS:
            began = time.perf_counter()
            result = transfer_motion(identity, driver_params, head, hand, placement)
            seconds = time.perf_counter() - began
            error = 1e3 * np.linalg.norm(
                posed_keypoints(result.params, head, hand)["hand_vertices"] - truth_hand, axis=2
            ).mean(axis=1)
            touching, kept = touches_kept(driver_params, result.params, head, hand)
            rows.append(
                {
                    "target": target,
                    "driver": driver,
                    "placement": placement,
                    "contact": contact.tolist(),
                    "error_mm": error.tolist(),
                    "seconds": seconds,
                    "frames": result.frames,
                    "touching_points": touching,
                    "kept_points": kept,
                }
            )
    return rows


def tables(rows: list[dict]) -> str:
    """The summary table and the per-frame tables (markdown)."""
    body = []
    for r in rows:
        err, contact = np.array(r["error_mm"]), np.array(r["contact"])
        touching = [f for f in r["frames"] if f["touching_points"]]
        body.append(
            [
                f"{r['target']} <- {r['driver']}",
                r["placement"],
                f"{err.mean():.1f}",
                f"{err[contact].mean():.1f}",
                f"{err[~contact].mean():.1f}",
                f"{err.max():.1f}",
                f"{np.mean([f['residual_mm'] for f in touching]):.1f}" if touching else "-",
                f"{r['kept_points'] / max(1, r['touching_points']):.0%}",
                f"{r['seconds']:.1f}",
            ]
        )
    out = [
        format_table(
            (
                "target <- driver",
                "placement",
                "hand error mean (mm)",
                "contact frames",
                "other frames",
                "worst frame",
                "touch residual (mm)",
                "touching points still touching",
                "seconds",
            ),
            body,
        ),
        "",
    ]
    for r in rows:
        if not r["frames"]:
            continue
        per = [
            [
                str(f["frame"]),
                "yes" if c else "",
                f"{e:.1f}",
                f"{s:.1f}",
                str(f["matched_points"]),
                str(f["touching_points"]),
                str(f["kept_points"]),
                f"{f['residual_mm']:.1f}",
                f"{f['moved_mm']:.1f}",
                f"{f['turned_deg']:.1f}",
            ]
            for f, c, e, s in zip(
                r["frames"],
                r["contact"],
                r["error_mm"],
                next(
                    q["error_mm"]
                    for q in rows
                    if (q["target"], q["driver"], q["placement"]) == (r["target"], r["driver"], "scaled")
                ),
            )
        ]
        out += [
            f"{r['target']} driven by {r['driver']}, per frame ({r['placement']}):",
            "",
            format_table(
                (
                    "frame",
                    "contact (truth)",
                    "error (mm)",
                    "scaled error (mm)",
                    "matched",
                    "touching",
                    "kept",
                    "residual (mm)",
                    "moved (mm)",
                    "turned (deg)",
                ),
                per,
            ),
            "",
        ]
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = measure()
    text = (
        f"# bench_transfer: cross-actor hand placement against the generator's\n\nCommit {commit()}; machine: "
        f"{cpu_name()}, {os.cpu_count()} cores, one torch thread; made "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n{tables(rows)}"
    )
    print(text)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "bench_transfer.md").write_text(text)
    (args.results / "bench_transfer.json").write_text(
        json.dumps({"commit": commit(), "machine": cpu_name(), "frames": FRAMES, "rows": rows}, indent=1)
    )


if __name__ == "__main__":
    main()
