"""Contact deformation (stage pbd): accuracy against the synthetic ground truth, and speed against accuracy.

The ground truth is the generator's closed-form soft-tissue field (avatar/synthetic/soft_tissue.py),
not PBD. Meshes are posed from the capture's ground-truth parameters, so only the solver is measured.
Errors are over the vertices that move (in the truth or the solve) in the contact frames, for the
solver and for zero offsets (the "w/o PBD" baseline) on the same vertices. Wall time is per
simulated (contact) frame, one torch thread; CPU seconds (the process's, over whole sequences, per
simulated frame) are the fairer number on a shared machine. Prints tables, asserts nothing.

Table 1: both subjects at draft (train + test frames). Table 2: method and sweep count against error
and time (--subject). Table 3: warm start against cold start at the defaults (--subject). The tables are
appended to ``benchmarks/results/bench_pbd.json`` (``--results``) with the commit and the machine.

Usage: python benchmarks/bench_pbd.py [--subject synth_a] [--sweeps 50,100,300,800] [--tables 1,2,3]
       [--results DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from avatar.pbd import PBDConfig, face_relative_stiffness, moving_vertex_errors, solve_sequence
from avatar.posing import posed_keypoints
from avatar.synthetic import SyntheticConfig, generate
from avatar.templates import procedural_hand, procedural_head

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.provenance import ResultLog, add_results_argument

#: quality=draft frame counts (conf/quality/draft.yaml)
DRAFT_FRAMES = {"train": 24, "test": 12}


def _sequence(subject: str, sequence: str, frames: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Posed face (T, V, 3) and hand (T, Vh, 3) and the true offsets (T, V, 3) of one draft sequence
    (rendered at a token resolution: only the motion and the soft tissue are used)."""
    cap = generate(SyntheticConfig(subject, sequence, image_size=16, num_frames=frames, supersample=1, num_cameras=2))
    posed = posed_keypoints(cap.params, procedural_head(), procedural_hand())
    return torch.from_numpy(posed["face_vertices"]), torch.from_numpy(posed["hand_vertices"]), cap.face_offsets


def _evaluate(data: list[tuple[torch.Tensor, torch.Tensor, np.ndarray]], cfg: PBDConfig) -> dict[str, float]:
    """Solve every sequence of ``data``; pooled errors (mm) and mean seconds per simulated frame."""
    head, hand = procedural_head(), procedural_hand()
    stiffness, _ = face_relative_stiffness(
        head.num_vertices, head.inner_distance, None, cfg.reference_thickness_m, cfg.stiffness_power
    )
    faces, hand_faces = torch.tensor(np.array(head.faces)), torch.tensor(np.array(hand.faces))
    preds, refs, seconds, penetration, cpu = [], [], [], 0.0, 0.0
    for face, hand_v, truth in data:
        began = time.process_time()
        results = solve_sequence(face, hand_v, faces, hand_faces, torch.from_numpy(stiffness), cfg)
        cpu += time.process_time() - began
        preds.append(np.stack([r.offsets.numpy() for r in results]))
        refs.append(truth)
        seconds += [r.seconds for r in results if r.simulated]
        penetration = max([penetration] + [r.penetration_max_m * 1e3 for r in results])
    ref = np.concatenate(refs)
    errors = moving_vertex_errors(np.concatenate(preds), ref, np.abs(ref).reshape(len(ref), -1).max(axis=1) > 0)
    assert errors is not None
    return {
        "mean": errors.mean_mm,
        "p95": errors.p95_mm,
        "zero_mean": errors.zero_mean_mm,
        "zero_p95": errors.zero_p95_mm,
        "ratio": errors.mean_mm / errors.zero_mean_mm,
        "s_per_frame": float(np.mean(seconds)),
        "cpu_per_frame": cpu / len(seconds),
        "frames": len(seconds),
        "penetration": penetration,
    }


def _table1(data: dict[str, list], base: PBDConfig, log: ResultLog) -> None:
    solver = (
        f"direct, at most {base.direct_outer} x {base.direct_inner} solves"
        if base.method == "direct"
        else f"{base.method}, Chebyshev rho {base.chebyshev_rho}, {base.iterations} sweeps"
    )
    rows = []
    for subject, seqs in data.items():
        r = _evaluate(seqs, base)
        rows.append(
            (
                subject,
                r["frames"],
                f"{r['mean']:.3f}",
                f"{r['p95']:.3f}",
                f"{r['zero_mean']:.3f}",
                f"{r['zero_p95']:.3f}",
                f"{r['ratio']:.0%}",
                f"{r['penetration']:.3f}",
                f"{r['s_per_frame']:.3f}",
                f"{r['cpu_per_frame']:.3f}",
            )
        )
    print(
        log.table(
            f"Table 1: accuracy on contact frames at draft (defaults: {solver}, shear {base.shear_stiffness})",
            (
                "subject",
                "contact frames",
                "mean error mm",
                "p95 mm",
                "zero offsets mean mm",
                "zero p95 mm",
                "mean / zero",
                "max residual penetration mm",
                "wall s per contact frame",
                "CPU s per contact frame",
            ),
            rows,
        ),
        flush=True,
    )


def _table2(data: list, base: PBDConfig, subject: str, sweep_counts: list[int], log: ResultLog) -> None:
    methods = {
        "Jacobi + Chebyshev": {"method": "jacobi"},
        "Jacobi": {"method": "jacobi", "chebyshev_rho": 0.0},
        "Gauss-Seidel": {"method": "gauss_seidel", "chebyshev_rho": 0.0},
    }
    runs = [
        (name, str(sweeps), replace(base, iterations=sweeps, **settings))
        for name, settings in methods.items()
        for sweeps in sweep_counts
    ]
    runs.append(
        (
            "Direct (the fixed point the sweeps converge to)",
            f"{base.direct_outer} x {base.direct_inner} solves at most",
            replace(base, method="direct"),
        )
    )
    rows = []
    for name, sweeps, cfg in runs:
        r = _evaluate(data, cfg)
        rows.append(
            (
                name,
                sweeps,
                f"{r['mean']:.3f}",
                f"{r['p95']:.3f}",
                f"{r['ratio']:.0%}",
                f"{r['s_per_frame']:.3f}",
                f"{r['cpu_per_frame']:.3f}",
            )
        )
    print(
        log.table(
            f"Table 2: sweeps against error and time ({subject}, draft, train + test)",
            (
                "solver",
                "sweeps",
                "mean error mm",
                "p95 mm",
                "mean / zero",
                "wall s per contact frame",
                "CPU s per contact frame",
            ),
            rows,
        ),
        flush=True,
    )


def _table3(data: list, base: PBDConfig, subject: str, log: ResultLog) -> None:
    rows = []
    for warm in (False, True):
        r = _evaluate(data, replace(base, warm_start=warm))
        rows.append(
            (
                "previous frame" if warm else "undeformed",
                f"{r['mean']:.3f}",
                f"{r['ratio']:.0%}",
                f"{r['s_per_frame']:.3f}",
                f"{r['cpu_per_frame']:.3f}",
            )
        )
    print(
        log.table(
            f"Table 3: warm start ({subject}, draft, defaults)",
            ("start", "mean error mm", "mean / zero", "wall s per contact frame", "CPU s per contact frame"),
            rows,
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subject", default="synth_a", help="subject of tables 2 and 3")
    parser.add_argument("--sweeps", default="50,100,300,800", help="sweep counts of table 2")
    parser.add_argument("--tables", default="1,2,3", help="which tables to print")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_pbd", preset="draft")
    torch.set_num_threads(1)
    base = PBDConfig()
    data = {s: [_sequence(s, seq, n) for seq, n in DRAFT_FRAMES.items()] for s in ("synth_a", "synth_b")}

    tables = {int(t) for t in args.tables.split(",")}
    if 1 in tables:
        _table1(data, base, log)
    if 2 in tables:
        print()
        _table2(data[args.subject], base, args.subject, [int(s) for s in args.sweeps.split(",")], log)
    if 3 in tables:
        print()
        _table3(data[args.subject], base, args.subject, log)
    log.write(args.results)


if __name__ == "__main__":
    main()
