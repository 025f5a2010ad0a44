"""Where the hand MLPs' gain lies, frame by frame: the hand PSNR of a trained stage-two model with some of its
delta heads switched off at evaluation, and of the warm-up model it started from.

Reads an outputs folder and trains nothing. For every frame of a split (``novel_view``: the training motion
from the held-out camera; ``self_reenact``: the held-out motion from the training cameras) it renders

- ``model``: the method's model as ``evaluate`` renders it;
- ``H_geo off``: H_geo's position, scale and rotation deltas set to zero;
- ``H_app off``: H_app's colour and opacity deltas set to zero;
- ``colour off`` / ``opacity off``: one of H_app's two heads set to zero;
- ``warm-up``: the static model of stage one (the method's ``warmup`` artifact) on the same meshes;

and prints the hand region's PSNR (dB, the pixels the split's masks label hand, as in ``evaluate``), averaged
over the split's cameras, with the share of the hand's vertices that project outside each training camera's
image (the crop padding there: frames stage, label 4). A head is switched off by zeroing its output layer for
the duration of one render; the model is not changed.

This is how the crop-padding A/B of docs/notes/crop-padding.md located the stage-two
seed's effect in H_app's colour deltas. Nothing here touches the held-out data during training: it only reads
trained models.

Usage: python benchmarks/hand_deltas.py --outputs DIR [--subject synth_a] [--method interactavatar] [--seed 0]
       [--split novel_view] [--set quality=draft fit.source=ground_truth ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from avatar.artifacts import load_views, method_params  # noqa: E402
from avatar.artifacts.motion import applied_deformation, load_sequence, templates  # noqa: E402
from avatar.geometry.views import ViewSet  # noqa: E402
from avatar.metrics import image_metrics  # noqa: E402
from avatar.representations.bound.dynamic_model import DynamicAvatar  # noqa: E402
from avatar.representations.bound.representation import load_dynamic, load_gaussians  # noqa: E402
from avatar.representations.bound.warmup import render_frame  # noqa: E402
from avatar.training.rendering import rasterize  # noqa: E402
from data_schemas.cameras import Camera, read_cameras  # noqa: E402
from data_schemas.capture import MASK_LABELS  # noqa: E402
from data_schemas.metrics import SPLIT_SOURCES  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from pipeline.workspace import method_run  # noqa: E402

#: variant -> {module of the dynamic model: its heads switched off}; ``None``: the warm-up model instead
VARIANTS: dict[str, dict[str, tuple[str, ...]] | None] = {
    "model": {},
    "H_geo off": {"hand_geo": ("mu", "s", "q")},
    "H_app off": {"hand_app": ("c", "o")},
    "colour off": {"hand_app": ("c",)},
    "opacity off": {"hand_app": ("o",)},
    "warm-up": None,
}


@contextmanager
def heads_off(model: DynamicAvatar, switched: dict[str, tuple[str, ...]]) -> Iterator[None]:
    """Zero the output layers of the named heads (``{"hand_app": ("c",)}``) of ``model`` while inside; restore
    them after. A zero output layer is exactly a zero delta (the heads' output layers start at zero too)."""
    saved = []
    with torch.no_grad():
        for module_name, heads in switched.items():
            module = getattr(model, module_name)
            if module is None:
                raise SystemExit(f"this model has no {module_name} (an ablation without it?)")
            for head in heads:
                out = module.heads[head].output
                saved.append((out, out.weight.clone(), out.bias.clone()))
                out.weight.zero_()
                out.bias.zero_()
    try:
        yield
    finally:
        with torch.no_grad():
            for out, weight, bias in saved:
                out.weight.copy_(weight)
                out.bias.copy_(bias)


def hand_psnr(views: ViewSet, image: torch.Tensor, frame: int, camera: int) -> float:
    """Hand-region PSNR (dB) of render ``image`` (S, S, 3) against crop (frame, camera); NaN without hand."""
    hand = views.labels[frame, camera] == MASK_LABELS["hand"]
    if not bool(hand.any()):
        return float("nan")
    gt, pred = views.target_and_render(image.clamp(0, 1), frame, camera)
    return float(image_metrics(pred.permute(2, 0, 1), gt.permute(2, 0, 1), hand)["psnr"])


def off_image_share(hand_vertices: np.ndarray, cameras: list[Camera]) -> list[float]:
    """Per camera, the share of ``hand_vertices`` (Vh, 3) that project outside its image (or behind it)."""
    shares = []
    for cam in cameras:
        uv, z = cam.project(hand_vertices)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        shares.append(float(1.0 - inside.mean()))
    return shares


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--outputs", type=Path, required=True)
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--method", default="interactavatar")
    parser.add_argument("--seed", type=int, default=0, help="the training run's seed (methods/<method>-seed<k>/)")
    parser.add_argument("--split", default="novel_view", choices=sorted(SPLIT_SOURCES))
    parser.add_argument("--set", nargs="*", default=[], help="config overrides the outputs were made with")
    args = parser.parse_args()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"subject={args.subject}",
                f"method={args.method}",
                f"seed={args.seed}",
                f"paths.outputs={args.outputs}",
                *args.set,
            ],
        )
    root = args.outputs / args.subject
    method_dir = root / "methods" / method_run(args.method, args.seed)
    model = load_dynamic(method_dir / "dynamic")
    part_names = tuple(json.loads((method_dir / "dynamic" / "model.json").read_text())["part_names"])
    warmup = load_gaussians(method_dir / "warmup", part_names)
    sequence, camera_split = SPLIT_SOURCES[args.split]
    views = load_views(root / "capture", root / "frames", sequence, camera_split)
    meshes, cond = load_sequence(
        root / "fit",
        sequence,
        cfg,
        pbd_dir=applied_deformation(cfg, root / "pbd"),
        params=method_params(method_dir / "dynamic", root / "fit", sequence),
    )
    train_cameras = sorted(
        (c for c in read_cameras(root / "capture" / "cameras.parquet") if c.split == "train"), key=lambda c: c.camera_id
    )
    face_vertices = templates(cfg.model)[0].num_vertices

    rows, table = [], []
    for t in range(views.num_frames):
        psnr = {}
        for name, switched in VARIANTS.items():
            with torch.no_grad():
                if switched is None:
                    images = [render_frame(warmup, meshes, views, t, c)[0].rgb for c in range(views.num_cameras)]
                else:
                    with heads_off(model, switched):
                        g = model(cond.frame(t), meshes.vertices[t])
                    images = [rasterize(g, views, c).rgb for c in range(views.num_cameras)]
            psnr[name] = float(np.nanmean([hand_psnr(views, image, t, c) for c, image in enumerate(images)]))
        off = off_image_share(meshes.vertices[t, face_vertices:].double().numpy(), train_cameras)
        rows.append(list(psnr.values()))
        table.append((t, *(f"{v:.2f}" for v in psnr.values()), " ".join(f"{s:.2f}" for s in off)))
    mean = np.nanmean(np.array(rows), axis=0)
    table.append(("mean", *(f"{v:.2f}" for v in mean), ""))
    print(
        f"{args.subject}, {method_run(args.method, args.seed)}, {args.split}: hand PSNR (dB) per frame; "
        f"last column: share of the hand off each training camera's image "
        f"({' '.join(c.camera_id for c in train_cameras)})"
    )
    print(format_table(("frame", *VARIANTS, "hand off-image"), table))


if __name__ == "__main__":
    main()
