"""Stage ``evaluate``: held-out camera (novel view) and held-out motion (self-reenactment) metrics."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from avatar.metrics import LPIPS, image_metrics
from avatar.preprocess.crops import label_box, overlap_box
from avatar.render.gaussians import resolve_backend
from avatar.training.dynamic import render_dynamic
from avatar.training.static import render_frame
from data_schemas.capture import MASK_LABELS
from data_schemas.images import write_png
from data_schemas.metrics import METRICS, REGIONS
from data_schemas.tables import write_table
from pipeline.stage import StageContext, stage
from stages.common import (
    contact_frames, load_dynamic, load_gaussians, load_sequence, load_views, model_sources,
)

#: split name -> (sequence, camera split) it renders
SPLIT_SOURCES = {"novel_view": ("train", "test"), "self_reenact": ("test", "train")}


@dataclass
class EvaluateConfig:
    """Types of ``stage.evaluate`` (values in conf/stage/evaluate.yaml)."""

    method: str
    dynamic_method: str
    grid_samples: int
    backend: str


Renderer = Callable[[int, int], torch.Tensor]


@stage("evaluate", inputs=("capture", "frames", "fit", "pbd", "warmup", "dynamic"),
       config_keys=("model", "stage.evaluate"), outputs=("metrics.parquet", "grids"), version="4",
       config_schema=EvaluateConfig, sources=model_sources)
def evaluate(ctx: StageContext) -> None:
    """Render the held-out camera and the held-out motion with the warm-up (static) model and the dynamic
    model; PSNR/SSIM/LPIPS per region; image grids comparing them."""
    conf = ctx.cfg.stage.evaluate
    cap_dir, frames_dir, fit_dir, pbd_dir = (ctx.input_dir(n) for n in ("capture", "frames", "fit", "pbd"))
    rows: dict[str, list] = {c.name: [] for c in METRICS.columns}
    lpips = LPIPS("alex")
    ctx.metrics["rasterizer"] = resolve_backend(conf.backend, torch.zeros(0, 3))  # what backend=auto chose here
    dynamic_model = load_dynamic(ctx.input_dir("dynamic"))
    (ctx.out_dir / "grids").mkdir()
    for split, (sequence, camera_split) in SPLIT_SOURCES.items():
        views = load_views(cap_dir, frames_dir, sequence, camera_split)
        meshes, cond = load_sequence(fit_dir, sequence, ctx.cfg, pbd_dir=pbd_dir)
        static_model = load_gaussians(ctx.input_dir("warmup"), meshes.part_names)
        renderers: dict[str, Renderer] = {
            conf.method: lambda t, c: render_frame(static_model, meshes, views, t, c, conf.backend)[0].rgb,
            conf.dynamic_method: lambda t, c: render_dynamic(dynamic_model, cond, meshes, views, t, c,
                                                             conf.backend)[0].rgb,
        }
        contact = contact_frames(cap_dir, sequence, views.num_frames)
        pairs = [(t, c) for t in range(views.num_frames) for c in range(views.num_cameras)]
        grid = []
        for i, (t, c) in enumerate(ctx.progress(pairs, desc=f"evaluate {split}")):
            gt = views.image(t, c).permute(2, 0, 1)
            preds = {}
            for method, render in renderers.items():
                with torch.no_grad():
                    preds[method] = render(t, c).clamp(0, 1).permute(2, 0, 1)
                for region, mask in _regions(views.labels[t, c].numpy()).items():
                    m = image_metrics(preds[method], gt, None if mask is None else torch.from_numpy(mask),
                                      lpips_model=lpips)
                    for key, value in (("method", method), ("split", split), ("camera_id", views.camera_ids[c]),
                                       ("frame", t), ("region", region), ("contact", bool(contact[t])),
                                       ("psnr", m["psnr"]), ("ssim", m["ssim"]), ("lpips", m["lpips"])):
                        rows[key].append(value)
            if i % max(len(pairs) // max(conf.grid_samples, 1), 1) == 0 and len(grid) < conf.grid_samples:
                grid.append(_grid_row(gt, list(preds.values())))
        write_png(ctx.out_dir / "grids" / f"{split}.png", np.concatenate(grid, axis=0))
    write_table(ctx.out_dir / "metrics.parquet", METRICS,
                {k: (v if METRICS.column(k).kind == "string" else np.asarray(v)) for k, v in rows.items()})
    for method in renderers:
        # the final (dynamic) model's figures also go unprefixed: they are what this pipeline produces
        for prefix in ((f"{method}_", "") if method == conf.dynamic_method else (f"{method}_",)):
            ctx.metrics.update(_summary(rows, method, prefix))


def _summary(rows: dict[str, list], method: str, prefix: str) -> dict[str, float]:
    """Mean full-image metrics per split of one method (and PSNR over the frames without contact)."""
    out = {}
    for split in SPLIT_SOURCES:
        full = [i for i, (m, s, r) in enumerate(zip(rows["method"], rows["split"], rows["region"]))
                if m == method and s == split and r == "full"]
        for metric in ("psnr", "ssim", "lpips"):
            out[f"{prefix}{split}_{metric}"] = float(np.nanmean([rows[metric][i] for i in full]))
        no_contact = [rows["psnr"][i] for i in full if not rows["contact"][i]]
        if no_contact:
            out[f"{prefix}{split}_psnr_no_contact"] = float(np.nanmean(no_contact))
    return out


def _regions(labels: np.ndarray) -> dict[str, np.ndarray | None]:
    """Region masks (S, S) bool of one crop; ``full`` is None (every pixel). ``interaction`` is the
    overlap of the hand and face boxes, empty when they do not overlap."""
    hand, face = labels == MASK_LABELS["hand"], labels == MASK_LABELS["face"]
    interaction = np.zeros_like(hand)
    box = overlap_box(label_box(labels, MASK_LABELS["hand"]), label_box(labels, MASK_LABELS["face"]))
    if box is not None:
        x0, y0, x1, y1 = box.astype(int)
        interaction[y0:y1, x0:x1] = True
    masks: dict[str, np.ndarray | None] = {"full": None, "hand": hand, "face": face, "interaction": interaction}
    assert tuple(masks) == REGIONS
    return masks


def _grid_row(gt: torch.Tensor, preds: list[torch.Tensor]) -> np.ndarray:
    """(S, (1 + 2M) S, 3) uint8: ground truth | each method's render | each method's error heat map (x4);
    images (3, S, S) in [0, 1]."""
    to_u8 = lambda x: (x.permute(1, 2, 0).numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8)  # noqa: E731

    def heat(pred: torch.Tensor) -> np.ndarray:
        err = ((pred - gt).abs().mean(0).numpy() * 4 * 255).clip(0, 255).astype(np.uint8)
        return cv2.applyColorMap(err, cv2.COLORMAP_INFERNO)[..., ::-1]

    return np.concatenate([to_u8(gt), *(to_u8(p) for p in preds), *(heat(p) for p in preds)], axis=1)
