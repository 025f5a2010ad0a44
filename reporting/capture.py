"""The report's sections on the capture: the run's introduction, the stages' table, the cameras and their rig, what
the scene contains."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from avatar.artifacts import (
    contact_frames,
    contact_source,
)
from avatar.posing import posed_keypoints
from avatar.render.rig_figure import SPLIT_NAMES, rig_figure
from avatar.templates import TemplateModel
from data_schemas import web_escape as esc
from data_schemas.cameras import Camera
from data_schemas.capture import CaptureIndex, SequenceInfo
from pipeline.summary import format_value
from reporting.html import figure_png, html_table, png_image


def intro(
    subject: str,
    method: str,
    label: str,
    quality: str,
    dataset: str,
    sequences: dict[str, SequenceInfo],
    num_cameras: int,
) -> str:
    """The title and the paragraph on what was run: subject, method, dataset, preset, cameras, sequences."""
    listed = ", ".join(f"{k} ({v.num_frames} frames, {v.width}x{v.height})" for k, v in sequences.items())
    return (
        f"<h1>InteractAvatar report: {esc.text(subject)}</h1>"
        f"<p>method <b>{esc.text(label)}</b> ({esc.text(method)}), dataset <b>{esc.text(dataset)}</b>, "
        f"quality preset <b>{esc.text(quality)}</b>, {num_cameras} cameras, sequences: {esc.text(listed)}</p>"
    )


def stages_table(manifests: dict[str, dict]) -> str:
    """Per upstream stage: wall time, peak memory, its metrics and when it was written (from its manifest)."""
    return html_table(
        ("stage", "wall s", "peak MB", "metrics", "written"),
        [
            (
                n,
                f"{m['timings']['wall_s']:.2f}",
                f"{m['peak_memory_mb']:.0f}",
                ", ".join(f"{k}={format_value(v)}" for k, v in sorted(m["metrics"].items())),
                m["created"],
            )
            for n, m in manifests.items()
        ],
    )


def cameras_table(cameras: list[Camera]) -> str:
    """Per capture camera: id, split, size, focal length and position."""
    return html_table(
        ("camera", "split", "size", "fx", "position (m)"),
        [
            (
                c.camera_id,
                c.split,
                f"{c.width}x{c.height}",
                f"{c.K[0, 0]:.1f}",
                np.array2string(c.cam_to_world[:3, 3], precision=3),
            )
            for c in cameras
        ],
    )


def contact_sheet_section(seq: str, frame: int, why: str, sheet_png: str, cameras: Sequence[Camera] = ()) -> str:
    """Every camera's crop of one frame in rows (``sheet_png``: base64 PNG of :func:`contact_sheet`), with what
    it shows and, given the ``cameras`` in the sheet's order, which tile is which."""
    order = ", ".join(f"{c.camera_id} ({SPLIT_NAMES.get(c.split, c.split)})" for c in cameras)
    caption = f"<figcaption>Row by row: {esc.text(order)}.</figcaption>" if order else ""
    return (
        f"<h2>All views, sequence '{esc.text(seq)}', frame {frame} ({esc.text(why)})</h2>"
        f"<figure>{png_image('contact sheet', sheet_png)}{caption}</figure>"
    )


def showcase_frame(cap_dir: Path, seq: str, index: CaptureIndex) -> tuple[int, str]:
    """First contact frame when ground truth says so, else the middle frame."""
    contact = contact_frames(cap_dir, seq, index.sequences[seq].num_frames)
    if contact.any():
        return int(np.flatnonzero(contact)[0]), "first frame with hand-face contact"
    return index.sequences[seq].num_frames // 2, "middle frame"


def contact_summary(cap_dir: Path, index: CaptureIndex) -> str:
    """Per sequence with contact labels, how many frames have contact and where the labels come from."""
    return contact_paragraph(
        {
            seq: (int(contact_frames(cap_dir, seq, info.num_frames).sum()), info.num_frames, source)
            for seq, info in index.sequences.items()
            if (source := contact_source(info)) is not None
        }
    )


def contact_paragraph(counts: dict[str, tuple[int, int, str]]) -> str:
    """The paragraph of :func:`contact_summary` from sequence -> (contact frames, frames, label source)."""
    parts = [f"{seq}: {n} of {total} frames with contact ({source})" for seq, (n, total, source) in counts.items()]
    return f"<p>{esc.text('; '.join(parts))}</p>" if parts else "<p>No contact labels in this capture.</p>"


def posed_meshes(
    params: Mapping[str, np.ndarray], frame: int, head: TemplateModel, hand: TemplateModel, with_hand: bool
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Part -> ((V, 3) world vertices, (F, 3) triangles) of the face (and hand) that ``params`` pose at ``frame``."""
    posed = posed_keypoints({k: np.asarray(v)[frame : frame + 1] for k, v in params.items()}, head, hand)
    meshes = {"face": (np.asarray(posed["face_vertices"][0]), np.asarray(head.faces))}
    if with_hand:
        meshes["hand"] = (np.asarray(posed["hand_vertices"][0]), np.asarray(hand.faces))
    return meshes


def rig_section(cameras: list[Camera], meshes: dict[str, tuple[np.ndarray, np.ndarray]], seq: str, frame: int) -> str:
    """The rig from above and from the front: the cameras (train and held-out in two colours, with their ids)
    around the fitted meshes of ``seq``'s ``frame`` (``meshes``: :func:`posed_meshes`)."""
    caption = (
        f"The cameras around the fitted meshes (sequence '{seq}', frame {frame}), in world space: blue the "
        "training cameras, orange the held-out one(s); each frustum drawn to a quarter of its distance from the "
        "subject, an id left out where it would cover another."
    )
    return (
        f"<figure>{png_image('the capture rig', figure_png(rig_figure(cameras, meshes)))}"
        f"<figcaption>{esc.text(caption)}</figcaption></figure>"
    )
