"""The report's section on what was modelled and why (the scene analysis) and on the contact deformation (the pbd
stage)."""

from __future__ import annotations

import json
from pathlib import Path

from data_schemas import web_escape as esc
from pipeline.summary import format_value
from reporting.html import html_table
from reporting.training import contact_draws_paragraph, selection_paragraph, withheld_paragraph


def scene_section(scene_dir: Path, manifests: dict[str, dict]) -> str:
    """The scene stage's decisions with their reasons, and the work they left out."""
    info = json.loads((scene_dir / "scene.json").read_text())
    rows = [
        (name.removeprefix("model_"), "yes" if info[name] else "no", info["why"][name])
        for name in ("model_hand", "model_pbd", "model_interaction")
    ]
    dynamic = manifests["dynamic"]["metrics"]
    work = (
        f"PBD simulated {manifests['pbd']['metrics'].get('simulated_frames', 0)} frames; the interaction MLPs "
        f"ran {dynamic.get('interaction_mlp_evaluations', 0)} Gaussian evaluations in training; "
        f"{len(info['deforming_triangles'])} of {info['face_triangles']} face triangles lie within d_max = "
        f"{info['d_max_m'] * 100:g} cm of the hand in some training contact frame (the only ones the interaction "
        f"module and PBD can reach). Decided on the '{info['decided_on']}' sequence; stage.scene.* overrides."
    )
    left_out = []
    if not info["model_hand"]:
        per_triangle = int(manifests["warmup"]["config"]["quality.gaussians_per_triangle"])
        left_out.append(
            f"{info['hand_triangles']} MANO triangles without Gaussians (about "
            f"{info['hand_triangles'] * per_triangle} Gaussians not created at this preset) "
            "and no hand MLPs"
        )
    if not info["model_pbd"]:
        left_out.append("no contact simulated in any frame")
    if not info["model_interaction"]:
        left_out.append("no interaction MLPs and no PointNet++")
    saved = (
        (
            "Left out: " + "; ".join(left_out) + ". benchmarks/bench_scene.py measures the time this saves "
            "against modelling everything (docs/explanation/scene.md)."
        )
        if left_out
        else ""
    )
    return (
        html_table(("modelled", "", "why"), rows)
        + f"<p>{esc.text(work)}</p>"
        + (f"<p>{esc.text(saved)}</p>" if saved else "")
        + contact_draws_paragraph(manifests["dynamic"])
        + withheld_paragraph(manifests["dynamic"])
        + selection_paragraph(dynamic)
    )


def pbd_section(pbd_dir: Path) -> str:
    """Where the face offsets came from and, per sequence, what was simulated and how close to the truth."""
    report = json.loads((pbd_dir / "pbd_report.json").read_text())
    rows = []
    for seq, entry in report["sequences"].items():
        frames = entry["frames"]
        simulated = [f for f in frames if f["simulated"]]
        errors = entry.get("ground_truth_error") or {}
        rows.append(
            (
                seq,
                len(frames),
                sum(f["near"] for f in frames),
                len(simulated),
                format_value(max((f["penetration_max_mm"] for f in simulated), default=0.0)),
                format_value(max(f["max_offset_mm"] for f in frames)),
                *(format_value(errors[k]) if k in errors else "-" for k in ("mean_mm", "zero_mean_mm")),
            )
        )
    table = html_table(
        (
            "sequence",
            "frames",
            "hand near the face",
            "simulated",
            "residual penetration mm",
            "largest offset mm",
            "vertex error mm",
            "zero offsets mm",
        ),
        rows,
    )
    stiffness = f", stiffness from {report['stiffness']}" if "stiffness" in report else ""
    intro = f"Offsets: {report['source']}{stiffness} ({report['frame_convention']})"
    return (
        f"<p>{esc.text(intro)}; frames whose hand stays clear of the face are not simulated. Vertex errors "
        f"over the vertices that move in contact frames, against ground truth where the capture has it.</p>{table}"
    )
