"""Stage ``evaluate``: held-out camera (novel view) and held-out motion (self-reenactment) metrics."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from avatar.metrics import LPIPS, image_metrics
from avatar.preprocess.crops import label_box
from avatar.render.gaussians import resolve_backend
from avatar.training.data import MeshSequence, ViewSet
from avatar.training.static import render_frame
from data_schemas.capture import MASK_LABELS
from data_schemas.images import write_png
from data_schemas.metrics import METRICS, REGIONS
from data_schemas.tables import write_table
from pipeline.stage import StageContext, stage
from stages.common import contact_frames, load_gaussians, load_meshes, load_views, model_sources

#: split name -> (sequence, camera split) it renders
SPLIT_SOURCES = {"novel_view": ("train", "test"), "self_reenact": ("test", "train")}


@dataclass
class EvaluateConfig:
    """Types of ``stage.evaluate`` (values in conf/stage/evaluate.yaml)."""

    method: str
    grid_samples: int
    backend: str


@stage("evaluate", inputs=("capture", "frames", "fit", "pbd", "warmup"), config_keys=("model", "stage.evaluate"),
       outputs=("metrics.parquet", "grids"), version="3", config_schema=EvaluateConfig,
       sources=model_sources)
def evaluate(ctx: StageContext) -> None:
    """Render the held-out camera and the held-out motion; PSNR/SSIM/LPIPS per region; image grids."""
    conf = ctx.cfg.stage.evaluate
    cap_dir, frames_dir = ctx.input_dir("capture"), ctx.input_dir("frames")
    rows: dict[str, list] = {c.name: [] for c in METRICS.columns}
    lpips = LPIPS("alex")
    ctx.metrics["rasterizer"] = resolve_backend(conf.backend, torch.zeros(0, 3))  # what backend=auto chose here
    (ctx.out_dir / "grids").mkdir()
    for split, (sequence, camera_split) in SPLIT_SOURCES.items():
        views = load_views(cap_dir, frames_dir, sequence, camera_split)
        meshes = load_meshes(ctx.input_dir("fit"), sequence, ctx.cfg, pbd_dir=ctx.input_dir("pbd"))
        model = load_gaussians(ctx.input_dir("warmup"), meshes.part_names)
        contact = contact_frames(cap_dir, sequence, views.num_frames)
        pairs = [(t, c) for t in range(views.num_frames) for c in range(views.num_cameras)]
        grid = []
        for i, (t, c) in enumerate(ctx.progress(pairs, desc=f"evaluate {split}")):
            pred, gt = _render(model, meshes, views, t, c, conf.backend)
            for region, mask in _regions(views.labels[t, c].numpy()).items():
                m = image_metrics(pred, gt, None if mask is None else torch.from_numpy(mask), lpips_model=lpips)
                for key, value in (("method", conf.method), ("split", split), ("camera_id", views.camera_ids[c]),
                                   ("frame", t), ("region", region), ("contact", bool(contact[t])), ("psnr", m["psnr"]), ("ssim", m["ssim"]),
                                   ("lpips", m["lpips"])):
                    rows[key].append(value)
            if i % max(len(pairs) // max(conf.grid_samples, 1), 1) == 0 and len(grid) < conf.grid_samples:
                grid.append(_grid_row(pred, gt))
        write_png(ctx.out_dir / "grids" / f"{split}.png", np.concatenate(grid, axis=0))
    write_table(ctx.out_dir / "metrics.parquet", METRICS,
                {k: (v if METRICS.column(k).kind == "string" else np.asarray(v)) for k, v in rows.items()})
    for split in SPLIT_SOURCES:
        for metric in ("psnr", "ssim", "lpips"):
            values = [v for s, r, v in zip(rows["split"], rows["region"], rows[metric]) if s == split and r == "full"]
            ctx.metrics[f"{split}_{metric}"] = float(np.nanmean(values))
        no_contact = [v for s, r, c, v in zip(rows["split"], rows["region"], rows["contact"], rows["psnr"])
                      if s == split and r == "full" and not c]
        if no_contact:
            ctx.metrics[f"{split}_psnr_no_contact"] = float(np.nanmean(no_contact))


def _render(model, meshes: MeshSequence, views: ViewSet, t: int, c: int,  # noqa: ANN001 - BoundGaussians
            backend: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Prediction and ground truth, (3, S, S) in [0, 1]."""
    with torch.no_grad():
        out, _ = render_frame(model, meshes, views, t, c, backend)
    return out.rgb.clamp(0, 1).permute(2, 0, 1), views.image(t, c).permute(2, 0, 1)


def _regions(labels: np.ndarray) -> dict[str, np.ndarray | None]:
    """Region masks (S, S) bool of one crop; ``full`` is None (every pixel). ``interaction`` is the
    overlap of the hand and face boxes, empty when they do not overlap."""
    hand, face = labels == MASK_LABELS["hand"], labels == MASK_LABELS["face"]
    interaction = np.zeros_like(hand)
    hb, fb = label_box(labels, MASK_LABELS["hand"]), label_box(labels, MASK_LABELS["face"])
    if hb is not None and fb is not None:
        x0, y0 = int(max(hb[0], fb[0])), int(max(hb[1], fb[1]))
        x1, y1 = int(min(hb[2], fb[2])), int(min(hb[3], fb[3]))
        if x1 > x0 and y1 > y0:
            interaction[y0:y1, x0:x1] = True
    masks: dict[str, np.ndarray | None] = {"full": None, "hand": hand, "face": face, "interaction": interaction}
    assert tuple(masks) == REGIONS
    return masks


def _grid_row(pred: torch.Tensor, gt: torch.Tensor) -> np.ndarray:
    """(S, 3S, 3) uint8: ground truth | render | error heat map (|error| x 4)."""
    to_u8 = lambda x: (x.permute(1, 2, 0).numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8)  # noqa: E731
    err = ((pred - gt).abs().mean(0).numpy() * 4 * 255).clip(0, 255).astype(np.uint8)
    heat = cv2.applyColorMap(err, cv2.COLORMAP_INFERNO)[..., ::-1]
    return np.concatenate([to_u8(gt), to_u8(pred), heat], axis=1)
