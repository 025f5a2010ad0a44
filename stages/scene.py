"""Stage ``scene``: look at the capture before modelling it (after ``fit``).

Per frame of every fitted sequence: in how many training cameras the hand shows (the frames stage's
masks), the smallest face-to-hand distance (the fitted meshes), contact (within d_max) and the face
vertices it reaches (``scene.parquet``). From the training sequence it decides what the downstream
stages model (``scene.json``): the hand (MANO Gaussians, hand MLPs), PBD, the interaction module, and
the triangles that can deform, each with its reason; ``stage.scene.<decision>`` overrides it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from avatar.artifacts.dependencies import TEMPLATE_KEYS, model_sources
from avatar.artifacts.motion import templates
from avatar.posing import posed_keypoints
from avatar.scene import DECISIONS, SceneFacts, decide, deforming_triangles, hand_face_distances, scene_facts
from data_schemas.capture import MASK_LABELS
from data_schemas.frames import FRAMES_INDEX, crop_mask_path
from data_schemas.images import read_png
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.scene import SCENE_FRAMES
from data_schemas.tables import SchemaError, read_table, write_table
from data_schemas.writes import write_json
from pipeline.stage import StageContext, stage

DECIDED_ON = "train"


@dataclass
class SceneConfig:
    """Types of ``stage.scene`` (values in conf/stage/scene.yaml)."""

    model_hand: str
    model_pbd: str
    model_interaction: str
    min_hand_area: float
    min_views: int
    min_hand_fraction: float

    @classmethod
    def validate(cls, conf: object) -> list[str]:
        """One line per decision that is not auto, true or false (YAML reads true/false as booleans)."""
        return [
            f"{name}={getattr(conf, name)!r}: choose auto, true or false"
            for name in DECISIONS
            if str(getattr(conf, name)).lower() not in ("auto", "true", "false")
        ]


@stage(
    "scene",
    inputs=("capture", "frames", "fit"),
    config_keys=(*TEMPLATE_KEYS, "stage.scene", "stage.dynamic.d_max"),
    outputs=("scene.json", "scene.parquet"),
    version="3",
    config_schema=SceneConfig,
    sources=model_sources,
)
def scene(ctx: StageContext) -> None:
    """scene.parquet (per frame: hand views, distance, contact) and scene.json (what to model, and why)."""
    conf, d_max = ctx.cfg.stage.scene, float(ctx.cfg.stage.dynamic.d_max)
    head, hand = templates(ctx.cfg.model)
    frames_dir, fit_dir = ctx.input_dir("frames"), ctx.input_dir("fit")
    sequences = sorted(p.parent.name for p in fit_dir.glob("*/params.parquet"))
    if DECIDED_ON not in sequences:
        raise SchemaError(f"{fit_dir}: no fitted '{DECIDED_ON}' sequence to analyse; rerun the fit stage")
    views, train_cameras = _hand_views(frames_dir, float(conf.min_hand_area))
    min_views = min(int(conf.min_views), train_cameras)  # a monocular capture sees the hand in one view at most
    facts: dict[str, SceneFacts] = {}
    for seq in ctx.progress(sequences, desc="scene: sequences"):
        table = read_table(fit_dir / seq / "params.parquet", PARAMS)
        posed = posed_keypoints({k: np.asarray(table[k]) for k in PARAM_COLUMNS}, head, hand)
        distances = hand_face_distances(posed["face_vertices"], posed["hand_vertices"])
        counts = np.array([views.get((seq, t), 0) for t in range(len(distances))])
        facts[seq] = scene_facts(counts, distances, min_views, d_max)
    train = facts[DECIDED_ON]
    decision = decide(train, float(conf.min_hand_fraction), {name: str(conf[name]).lower() for name in DECISIONS})
    triangles = deforming_triangles(train.near_vertices, np.asarray(head.faces))
    _write_frames(ctx, facts)
    write_json(
        ctx.out_dir / "scene.json",
        {
            **asdict(decision),
            "reasons": decision.reasons,
            "decided_on": DECIDED_ON,
            "d_max_m": d_max,
            "thresholds": {
                "min_hand_area": float(conf.min_hand_area),
                "min_views": min_views,
                "min_hand_fraction": float(conf.min_hand_fraction),
            },
            "sequences": {seq: _summary(f) for seq, f in facts.items()},
            "deforming_triangles": np.flatnonzero(triangles).tolist(),
            "face_triangles": len(head.faces),
            "hand_triangles": len(hand.faces),
        },
        "scene analysis",
    )
    ctx.metrics.update({name: getattr(decision, name) for name in DECISIONS})
    ctx.metrics.update(
        {
            "hand_frames": int(train.hand_present.sum()),
            "contact_frames": int(train.contact.sum()),
            "deforming_triangles": int(triangles.sum()),
        }
    )


def _hand_views(frames_dir: Path, min_area: float) -> tuple[dict[tuple[str, int], int], int]:
    """(sequence, frame) -> training cameras whose crop mask shows at least ``min_area`` of hand; and the
    number of training cameras."""
    index = read_table(frames_dir / "index.parquet", FRAMES_INDEX)
    counts: dict[tuple[str, int], int] = {}
    for seq, camera, frame, split in zip(index["sequence"], index["camera_id"], index["frame"], index["split"]):
        if split != "train":  # the held-out camera is test data: decisions never look at it
            continue
        labels = read_png(crop_mask_path(frames_dir, seq, camera, int(frame)), 1)
        seen = float((labels == MASK_LABELS["hand"]).mean()) >= min_area
        counts[(seq, int(frame))] = counts.get((seq, int(frame)), 0) + int(seen)
    return counts, len({c for c, split in zip(index["camera_id"], index["split"]) if split == "train"})


def _summary(facts: SceneFacts) -> dict:
    """Counts and the closest approach of one sequence."""
    closest = float(np.nanmin(facts.distance_m)) * 1e3 if facts.hand_present.any() else None
    return {
        "frames": len(facts.contact),
        "hand_frames": int(facts.hand_present.sum()),
        "contact_frames": int(facts.contact.sum()),
        "closest_mm": closest,
    }


def _write_frames(ctx: StageContext, facts: dict[str, SceneFacts]) -> None:
    """scene.parquet: one row per frame of every sequence."""
    rows: dict[str, list] = {name: [] for name in SCENE_FRAMES.column_names}
    for seq, f in facts.items():
        T = len(f.contact)
        rows["sequence"] += [seq] * T
        for name, values in (
            ("frame", np.arange(T)),
            ("hand_views", f.hand_views),
            ("hand_present", f.hand_present),
            ("distance_m", f.distance_m),
            ("contact", f.contact),
            ("near_vertices", f.near_vertices.sum(axis=1)),
        ):
            rows[name].append(values)
    write_table(
        ctx.out_dir / "scene.parquet",
        SCENE_FRAMES,
        {k: (v if k == "sequence" else np.concatenate(v)) for k, v in rows.items()},
    )
