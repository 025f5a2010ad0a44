"""``metrics.parquet``: image quality per method, split, camera, frame and region; ``comparison.parquet``:
the methods side by side.

``split``: ``novel_view`` (held-out camera, train motion), ``self_reenact``
(train cameras, held-out test motion posed as the fit tracked it), ``self_reenact_tracked`` (the held-out motion
tracked by the trained avatar on some training cameras, scored on the others: ``stage.evaluate.test_tracking``)
or ``cross_reenact`` (train cameras, another subject's held-out
motion transferred onto this one, against the synthetic ground truth of this identity performing it).
``region``: ``full``, ``hand``, ``face``, ``interaction`` (the overlap of the hand and face boxes). A metric
is NaN where the region is absent from the ground-truth frame.
"""

from __future__ import annotations

from pathlib import Path

from data_schemas.tables import Column, TableSchema

METRICS = TableSchema(
    name="metrics",
    version=1,
    columns=(
        Column("method", "string"),
        Column("split", "string"),
        Column("camera_id", "string"),
        Column("frame", "int32"),
        Column("region", "string"),
        Column("contact", "bool", doc="hand touches the face in this frame (ground truth; False when unknown)"),
        Column("psnr", "float32", unit="dB", finite=False),
        Column("ssim", "float32", finite=False),
        Column("lpips", "float32", finite=False),
    ),
)
TRACKED_SPLIT = "self_reenact_tracked"  # with stage.evaluate.test_tracking=avatar
SPLITS = ("novel_view", "self_reenact", TRACKED_SPLIT, "cross_reenact")  # cross_reenact: when reenact.driver names one
REGIONS = ("full", "hand", "face", "interaction")
#: split -> (sequence it renders, camera split it renders from)
SPLIT_SOURCES = {"novel_view": ("train", "test"), "self_reenact": ("test", "train")}
#: the frames a comparison row averages over
CONTACT_GROUPS = ("all", "contact", "no_contact")

COMPARISON = TableSchema(
    name="comparison",
    version=2,  # 2: one row per training seed (column seed)
    columns=(
        Column("method", "string"),
        Column("seed", "int32", doc="the training run's seed (root key seed; method_run names its folder)"),
        Column("label", "string", doc="the method's name in the paper's tables, e.g. 'w/o I'"),
        Column("split", "string"),
        Column("region", "string"),
        Column("contact", "string", doc="frames averaged: 'all', 'contact' or 'no_contact'"),
        Column("images", "int32", doc="images where the region is present"),
        Column("psnr", "float32", unit="dB", finite=False),
        Column("ssim", "float32", finite=False),
        Column("lpips", "float32", finite=False),
        Column("train_steps", "int32", doc="warm-up plus stage-two optimisation steps"),
        Column(
            "train_wall_s",
            "float32",
            unit="s",
            doc="warm-up plus stage-two wall time (a shared warm-up "
            "counts in full for each method that starts from it)",
        ),
        Column("gaussians", "int64", doc="Gaussians of the trained model"),
    ),
)


def showcase_path(evaluate_dir: Path, split: str, frame: int, camera_id: str) -> Path:
    """Where stage evaluate keeps its render of one showcase (frame, camera) of ``split`` (the same frames
    for every method: the comparison's image rows)."""
    return evaluate_dir / "renders" / split / f"{frame:05d}_{camera_id}.png"
