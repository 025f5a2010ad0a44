"""Fitting accuracy and speed on the synthetic capture (prints a table, no asserts).

Conditions: ground-truth keypoints of the train views with 1-px Gaussian noise,
and with 3-px noise plus 10% outliers. Columns: hand MPJPE (21 keypoints, mm),
face landmark error (68 landmarks, mm), mean reprojection error (px) of the
detections the fit used, and fit time per frame per view (ms). The table is appended to
``benchmarks/results/bench_fitting.json`` (``--results``) with the commit and the machine.

Usage: python benchmarks/bench_fitting.py [--size 256] [--frames 12] [--results DIR]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from avatar.fitting import FitConfig, corrupt_keypoints, fit_sequence, landmark_error, mpjpe
from avatar.synthetic import SyntheticConfig, generate
from avatar.templates import FLAMELayer, MANOLayer, procedural_hand, procedural_head

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.provenance import ResultLog, add_results_argument

HAND_KEYS = ("mano_shape", "mano_hand_pose", "mano_global_orient", "mano_transl")
FACE_KEYS = (
    "flame_shape",
    "flame_expression",
    "flame_global_orient",
    "flame_neck_pose",
    "flame_jaw_pose",
    "flame_eye_pose",
    "flame_transl",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--frames", type=int, default=12)
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_fitting")
    torch.set_num_threads(1)
    cap = generate(
        SyntheticConfig(
            subject="synth_a", sequence="train", image_size=args.size, num_frames=args.frames, supersample=1
        )
    )
    head, hand = procedural_head(), procedural_hand()
    mano = MANOLayer(hand)

    def hand_kp(params: dict[str, np.ndarray]) -> np.ndarray:
        out = mano(*[torch.as_tensor(params[k]) for k in HAND_KEYS])
        return mano.keypoints21(out.vertices, out.joints).detach().numpy()

    def face_lmk(params: dict[str, np.ndarray]) -> np.ndarray:
        flame = FLAMELayer.for_params(head, params)
        return flame.landmarks(flame(*[torch.as_tensor(params[k]) for k in FACE_KEYS]).vertices).detach().numpy()

    train = [c for c in cap.cameras if c.split == "train"]
    rows = []
    for name, noise, outliers in (("1px noise", 1.0, 0.0), ("3px noise + 10% outl.", 3.0, 0.1)):
        rng = np.random.default_rng(0)
        kp = {
            c.camera_id: {
                part: corrupt_keypoints(arr, noise, 0.0, outliers, args.size, rng)
                for part, arr in cap.keypoints[c.camera_id].items()
            }
            for c in train
        }
        res = fit_sequence(kp, train, head, hand, FitConfig())
        rows.append(
            (
                name,
                f"{mpjpe(hand_kp(res.params), hand_kp(cap.params)):.2f}",
                f"{landmark_error(face_lmk(res.params), face_lmk(cap.params)):.2f}",
                f"{np.nanmean(res.reprojection_px['hand']):.2f}",
                f"{np.nanmean(res.reprojection_px['face']):.2f}",
                f"{res.timing['per_frame_per_view_ms']:.1f}",
            )
        )
    print(
        log.table(
            f"synth_a/train, {args.frames} frames, {len(train)} train views at {args.size} px, 1 torch thread",
            ("condition", "hand MPJPE mm", "face lmk mm", "hand px", "face px", "ms/frame/view"),
            rows,
        )
    )
    log.write(args.results)


if __name__ == "__main__":
    main()
