"""The report's picture of the capture rig: the cameras' frusta, with their ids, around the posed meshes in world
space, seen from above and from the front (a helper of ``stages/report.py``, not a stage).

The views' axes come from the cameras, not from a dataset's world convention: *up* is the cameras' mean up
(OpenCV: minus the image's y axis), *front* the side of the subject the cameras stand on (the mean camera centre
seen from the meshes' centre, made level). Both views share the horizontal axis (the viewer's right, facing the
subject from the cameras' side) and put the meshes' centre at the origin, in metres.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from data_schemas.cameras import Camera

#: camera colours by split (matplotlib colour names)
SPLIT_COLOURS = {"train": "tab:blue", "test": "tab:orange"}
SPLIT_NAMES = {"train": "training camera", "test": "held-out camera"}
#: mesh colours by part (RGB in [0, 1]), shaded by how squarely a triangle faces the viewer
PART_COLOURS = {"face": (0.72, 0.72, 0.74), "hand": (0.85, 0.62, 0.42)}
PART_NAMES = {"face": "head (FLAME)", "hand": "hand (MANO)"}


def rig_axes(cameras: list[Camera], centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, front) orthonormal world directions of the rig picture: ``up`` the cameras' mean up, ``front``
    from ``centre`` (3,) toward the mean camera centre, made level, ``right = up x front``. Falls back to the
    cameras' mean viewing direction, then to any level direction, where the cameras surround the subject."""
    up = -np.mean([c.cam_to_world[:3, 1] for c in cameras], axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 1.0, 0.0])
    candidates = [
        np.mean([c.cam_to_world[:3, 3] for c in cameras], axis=0) - centre,
        -np.mean([c.cam_to_world[:3, 2] for c in cameras], axis=0),
        np.eye(3)[int(np.argmin(np.abs(up)))],
    ]
    for front in candidates:
        front = front - up * float(front @ up)
        if np.linalg.norm(front) > 1e-6:
            break
    front = front / np.linalg.norm(front)
    return np.cross(up, front), up, front


def rig_figure(cameras: list[Camera], meshes: dict[str, tuple[np.ndarray, np.ndarray]]) -> Any:
    """A matplotlib Figure of two orthographic views of the rig: from above (the cameras' side at the bottom) and
    from the front (as the cameras see the subject). Each camera is its frustum (to a quarter of its distance from
    the subject), coloured by split and labelled with its id (where the label overlaps none); ``meshes`` (part ->
    (V, 3) world vertices in metres, (F, 3) triangles) are drawn filled and shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    centres = np.stack([c.cam_to_world[:3, 3] for c in cameras])
    points = np.concatenate([v for v, _ in meshes.values()]) if meshes else centres
    centre = 0.5 * (points.min(0) + points.max(0))
    right, up, front = rig_axes(cameras, centre)
    depth = 0.25 * float(np.median(np.linalg.norm(centres - centre, axis=1)))
    # per view: the plot's (x, y) axes and the direction toward the viewer (for shading and drawing order)
    views = (("from above", right, -front, up), ("from the front", right, up, front))
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.2), dpi=100)
    for ax, (title, x_axis, y_axis, toward) in zip(axes, views):

        def plane(p: np.ndarray, x_axis: np.ndarray = x_axis, y_axis: np.ndarray = y_axis) -> np.ndarray:
            return np.stack([(p - centre) @ x_axis, (p - centre) @ y_axis], axis=-1)

        for part, (vertices, faces) in meshes.items():
            tri = vertices[faces]  # (F, 3, 3)
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            # outward normals (whatever the winding): the triangles facing away are hidden, and not drawn
            normals *= 1.0 if float(np.sum((tri.mean(1) - vertices.mean(0)) * normals)) >= 0 else -1.0
            facing = np.flatnonzero(normals @ toward > 0)
            order = facing[np.argsort(tri[facing].mean(1) @ toward)]  # far first
            shade = 0.45 + 0.55 * (normals[order] @ toward)
            colours = np.clip(shade[:, None] * np.asarray(PART_COLOURS.get(part, (0.6, 0.6, 0.6))), 0, 1)
            ax.add_collection(
                PolyCollection(
                    list(plane(tri[order])), facecolors=colours, edgecolors="none", antialiaseds=False, zorder=1
                )
            )
        # an id that would overlap one already written is left out (e.g. cameras at one height, seen from the front)
        labelled: list[np.ndarray] = []
        label_size = np.array([0.1, 0.04]) * float(np.ptp(plane(np.concatenate([centres, points])), axis=0).max())
        for cam, c in zip(cameras, centres):
            inv_k = np.linalg.inv(cam.K)
            corners = [(0, 0), (cam.width, 0), (cam.width, cam.height), (0, cam.height)]
            rays = np.array([inv_k @ (u, v, 1.0) for u, v in corners]) * depth
            ends = plane(rays @ cam.cam_to_world[:3, :3].T + c)
            at = plane(c)
            colour = SPLIT_COLOURS.get(cam.split, "tab:gray")
            for end in ends:
                ax.plot(*np.stack([at, end]).T, color=colour, linewidth=0.8, zorder=2)
            ax.plot(*np.vstack([ends, ends[:1]]).T, color=colour, linewidth=0.8, zorder=2)
            ax.plot(*at, marker="o", markersize=3, color=colour, zorder=3)
            if any((np.abs(at - q) < label_size).all() for q in labelled):
                continue
            labelled.append(at)
            # from above: the label behind the camera, away from its frustum (for a camera seen along its axis, away
            # from the subject); from the front, where frusta point sideways, above it
            behind = at - ends.mean(0)
            outward = (behind if np.linalg.norm(behind) > 0.25 * depth else at) if toward is up else np.array([0, 1])
            outward = outward / max(float(np.linalg.norm(outward)), 1e-9)
            ax.annotate(
                cam.camera_id,
                at,
                xytext=tuple(5 * outward),
                textcoords="offset points",
                ha="right" if outward[0] < -0.4 else "left" if outward[0] > 0.4 else "center",
                va="top" if outward[1] < -0.4 else "bottom" if outward[1] > 0.4 else "center",
                fontsize=7,
                color=colour,
                bbox={"boxstyle": "square,pad=0.1", "facecolor": "white", "edgecolor": "none", "alpha": 0.7},
                parse_math=False,  # an id is text: a '$' is no formula
                annotation_clip=False,
                zorder=4,
            )
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        ax.margins(0.12)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("right (m)", fontsize=8)
        ax.set_ylabel("front  \u2190  (m)  \u2192  back" if title == "from above" else "up (m)", fontsize=8)
    handles = [
        Line2D([], [], color=SPLIT_COLOURS[s], marker="o", markersize=3, label=SPLIT_NAMES[s])
        for s in SPLIT_COLOURS
        if any(c.split == s for c in cameras)
    ] + [Patch(color=PART_COLOURS[p], label=PART_NAMES[p]) for p in meshes if p in PART_COLOURS]
    axes[1].legend(handles=handles, fontsize=7, loc="best")
    return fig
