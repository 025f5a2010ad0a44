"""The report's sections on reenactment and on the browser viewer."""

from __future__ import annotations

import json
from pathlib import Path

from data_schemas import web_escape as esc
from pipeline.manifest import MANIFEST_NAME
from reporting.html import base64_file


def reenact_section(reenact_dir: Path) -> str:
    """Who drove the avatar, the contact it made, the render speed, and the videos (playable in the page)."""
    info = json.loads((reenact_dir / "reenact_report.json").read_text())
    metrics = json.loads((reenact_dir / MANIFEST_NAME).read_text())["metrics"]
    simulated = [f for f in info["pbd"]["frames"] if f["simulated"]]
    worst = max((f["penetration_max_mm"] for f in simulated), default=0.0)
    text = (
        f"Driver: {info['driver']}, {info['frames']} frames, head-size ratio {info['head_scale']:.3f}; contact "
        + (
            f"simulated on {len(simulated)} frames (worst residual penetration {worst:.2f} mm)"
            if info["pbd"]["simulated"]
            else "not simulated (the method has no PBD)"
        )
        + f"; {metrics['frames_per_second']:.1f} frames per second at {metrics['image_size']} px "
        f"(model {metrics['model_ms_per_frame']:.0f} ms per frame, rasterizer "
        f"{metrics['render_ms_per_view']:.0f} ms per view)."
    )
    transfer = info.get("transfer", {"frames": []})
    touching = [f for f in transfer["frames"] if f["touching_points"]]
    if touching:
        text += (
            f" The driver's hand touches its face in {len(touching)} frames; placed to keep those touches "
            f"(reenact.placement={transfer['placement']}), {metrics['transfer_kept_fraction']:.0%} of the "
            f"touching points touch this face too, a mean {metrics['transfer_residual_mm']:.1f} mm from the "
            f"same surface points."
        )
    if info.get("sequence_note"):  # e.g. a capture without the held-out motion reenacts its training motion
        text += f" {info['sequence_note'][0].upper()}{info['sequence_note'][1:]}."
    truth = info["ground_truth"]
    text += (
        f" Beside the ground truth ({truth['sequence']}) on camera(s) {', '.join(truth['cameras'])}."
        if truth["cameras"]
        else f" No ground truth to show: {truth['note']}."
    )
    shown = []  # per view: reenacted | ground truth where the capture has it, else the reenactment alone
    for path in sorted((reenact_dir / "videos").glob("*.mp4")):
        if path.stem.endswith(("_gt", "_vs_gt")):
            continue
        paired = path.with_name(f"{path.stem}_vs_gt.mp4")
        shown.append((paired, f"{path.stem}: reenacted | ground truth") if paired.is_file() else (path, path.stem))
    videos = "".join(
        f"<figure style='display:inline-block;margin:4px'><video controls autoplay loop muted playsinline "
        f"src='data:video/mp4;base64,{base64_file(path)}'></video><figcaption>{esc.text(caption)}</figcaption>"
        f"</figure>"
        for path, caption in shown
    )
    return f"<p>{esc.text(text)}</p>{videos}"


def viewer_section(viewer_dir: Path) -> str:
    """Links to this method's browser viewer and to the other methods' (those written by now), with its sizes."""
    info = json.loads((viewer_dir / "viewer.json").read_text())
    others = sorted(p for p in viewer_dir.parent.parent.glob("*/viewer/index.html") if p.parent != viewer_dir)
    links = "".join(
        f" <a href='../../{esc.url_path(name, 'viewer', 'index.html')}'>{esc.text(name)}</a>"
        for name in (p.parent.parent.name for p in others)
    )
    built = (
        ""
        if info["page_built"]
        else f" The page is not built on this machine: run <code>{esc.text(info['build_command'])}</code>, then "
        "<code>interactavatar run.only=viewer</code>."
    )
    return (
        f"<p><a href='../viewer/index.html'>Open this avatar in the viewer</a>: orbit it, play its motions, step "
        f"through the frames beside the ground truth (from a server: <code>interactavatar-view "
        f"&lt;outputs&gt;/&lt;subject&gt;</code>).{built} {esc.text(info['gaussians'])} Gaussians, "
        f"{info['bytes_per_frame'] / 1e3:.0f} kB per frame, {info['mb_per_100_frames']:.1f} MB per 100 frames."
        + (f" The other methods' viewers:{links}." if links else "")
        + "</p>"
    )
