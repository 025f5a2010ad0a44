"""The procedural head fits heads it was not built from (issue: own footage).

A head outside the template's shape space is made by deforming the template
with a smooth random field (Gaussian bumps of 5 cm, up to ~2.5 cm displacement);
its landmarks, projected without noise into the synthetic capture's train
cameras, are fitted with the full template and with its designed identity
columns only. Goal: a reprojection residual within 1.5x of a 0.5 px keypoint
noise, i.e. under 0.75 px.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from avatar.fitting import FitConfig, fit_sequence, landmark_error
from avatar.synthetic import SyntheticCapture, SyntheticConfig, generate
from avatar.templates import FLAMELayer, TemplateModel, procedural_hand, procedural_head
from avatar.templates.head import NUM_DESIGNED_SHAPE

FACE_KEYS = (
    "flame_shape",
    "flame_expression",
    "flame_global_orient",
    "flame_neck_pose",
    "flame_jaw_pose",
    "flame_eye_pose",
    "flame_transl",
)
GOAL_PX = 1.5 * 0.5


@pytest.fixture(scope="module")
def capture() -> SyntheticCapture:
    """256 px like the measurement in the README (pixels at the subject scale with the image)."""
    return generate(SyntheticConfig(subject="synth_a", sequence="train", image_size=256, num_frames=3, supersample=1))


def _smooth_field(vertices: np.ndarray, seed: int, amplitude_m: float = 0.008) -> np.ndarray:
    """(V, 3) sum of 8 Gaussian bumps (sigma 5 cm) at random vertices with random displacements."""
    rng = np.random.default_rng(seed)
    field = np.zeros_like(vertices)
    for centre in vertices[rng.choice(len(vertices), 8, replace=False)]:
        weight = np.exp(-np.sum((vertices - centre) ** 2, axis=1) / (2 * 0.05**2))
        field += weight[:, None] * rng.normal(0.0, amplitude_m, 3)
    return field


def _designed_only(head: TemplateModel) -> TemplateModel:
    """The head with only its designed identity columns (what the template had before widening)."""
    columns = np.r_[np.arange(NUM_DESIGNED_SHAPE), np.arange(head.num_shape, head.num_shapes_total)]
    return dataclasses.replace(
        head, shapedirs=head.shapedirs[:, :, columns], num_shape=NUM_DESIGNED_SHAPE, shape_roughness=None
    )


def _landmarks(model: TemplateModel, params: dict[str, np.ndarray]) -> np.ndarray:
    layer = FLAMELayer.for_params(model, params)
    return layer.landmarks(layer(*[torch.as_tensor(params[k]) for k in FACE_KEYS]).vertices).numpy()


@pytest.mark.parametrize("seed", [1, pytest.param(3, marks=pytest.mark.slow)])
def test_fit_reaches_a_head_outside_the_designed_space(capture: SyntheticCapture, seed: int) -> None:
    head, hand = procedural_head(), procedural_hand()
    field = _smooth_field(np.array(head.v_template), seed)
    other = dataclasses.replace(head, v_template=head.v_template + field)
    truth = _landmarks(other, capture.params)  # (T, 68, 3)
    train = [c for c in capture.cameras if c.split == "train"]
    keypoints = {}
    for camera in train:
        uv, _ = camera.project(truth)
        keypoints[camera.camera_id] = {
            "face": np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], -1),
            "hand": capture.keypoints[camera.camera_id]["hand"],
        }
    residual, error = {}, {}
    for name, model in (("widened", head), ("designed", _designed_only(head))):
        fit = fit_sequence(keypoints, train, model, hand, FitConfig())
        residual[name] = float(np.nanmean(fit.reprojection_px["face"]))
        error[name] = landmark_error(_landmarks(model, fit.params), truth)
    # Measured (seeds 1, 3): widened 0.22 / 0.21 px, 0.42 / 0.37 mm; designed only 1.75 / 2.52 px, 3.2 / 4.4 mm.
    assert residual["widened"] < GOAL_PX < residual["designed"], residual
    assert error["widened"] < 0.5 * error["designed"] and error["widened"] < 1.0, error


def test_identity_space_follows_the_detector() -> None:
    """auto frees the whole identity space only for unbiased (ground-truth) keypoints; core keeps to the
    procedural head's designed columns; an official model without a core space is fitted whole."""
    from stages.fit import face_shape_columns

    head = procedural_head()
    assert face_shape_columns(head, "auto", "ground_truth") is None
    assert face_shape_columns(head, "auto", "mediapipe") == NUM_DESIGNED_SHAPE
    assert face_shape_columns(head, "auto", "provided") == NUM_DESIGNED_SHAPE
    assert face_shape_columns(head, "core", "ground_truth") == NUM_DESIGNED_SHAPE
    assert face_shape_columns(head, "full", "mediapipe") is None
    assert face_shape_columns(dataclasses.replace(head, num_core_shape=None), "core", "mediapipe") is None
    from data_schemas.tables import SchemaError

    with pytest.raises(SchemaError, match="identity_space='wide'"):
        face_shape_columns(head, "wide", "mediapipe")


def test_a_fit_keeps_to_the_columns_it_is_given(capture: SyntheticCapture) -> None:
    """face_shape_columns=10 fits a 10-wide flame_shape (the synthetic subject's own space) and recovers it."""
    train = [c for c in capture.cameras if c.split == "train"][:4]
    keypoints = {c.camera_id: capture.keypoints[c.camera_id] for c in train}
    fit = fit_sequence(
        keypoints,
        train,
        procedural_head(),
        procedural_hand(),
        FitConfig(face_shape_columns=NUM_DESIGNED_SHAPE, coarse_iterations=40, fine_iterations=80),
    )
    assert fit.params["flame_shape"].shape == (capture.params["flame_shape"].shape[0], NUM_DESIGNED_SHAPE)
    truth = _landmarks(procedural_head(), capture.params)
    assert landmark_error(_landmarks(procedural_head(), fit.params), truth) < 1.0
