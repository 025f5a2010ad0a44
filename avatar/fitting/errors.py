"""Accuracy metrics of a fit against ground truth, in millimetres."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from avatar.posing import posed_keypoints
from avatar.templates import TemplateModel

MM_PER_M = 1000.0


def per_point_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean distances (..., N) in mm between points (..., N, 3) in metres."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"need matching (..., N, 3) arrays, got {pred.shape} and {gt.shape}")
    return np.linalg.norm(pred - gt, axis=-1) * MM_PER_M


def mpjpe(pred_joints: np.ndarray, gt_joints: np.ndarray) -> float:
    """Mean per-joint position error (mm) of joints (..., J, 3) in metres."""
    return float(per_point_error(pred_joints, gt_joints).mean())


def per_vertex_error(pred_vertices: np.ndarray, gt_vertices: np.ndarray) -> np.ndarray:
    """Per-vertex error (..., V) in mm of vertices (..., V, 3) in metres."""
    return per_point_error(pred_vertices, gt_vertices)


def landmark_error(pred_landmarks: np.ndarray, gt_landmarks: np.ndarray) -> float:
    """Mean landmark distance (mm) of landmarks (..., L, 3) in metres."""
    return float(per_point_error(pred_landmarks, gt_landmarks).mean())


def tracking_errors(
    params: Mapping[str, np.ndarray], gt: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel
) -> dict[str, float]:
    """Hand MPJPE (21 keypoints), face landmark error and mean per-vertex errors (mm) of the posed ``params``
    against the posed ``gt`` (params.parquet columns, T rows each), over every frame."""
    pred, true = posed_keypoints(params, head, hand), posed_keypoints(gt, head, hand)
    return {
        "mpjpe_hand_mm": mpjpe(pred["hand"], true["hand"]),
        "mpjpe_face_mm": landmark_error(pred["face"], true["face"]),
        "vertex_error_hand_mm": float(per_vertex_error(pred["hand_vertices"], true["hand_vertices"]).mean()),
        "vertex_error_face_mm": float(per_vertex_error(pred["face_vertices"], true["face_vertices"]).mean()),
    }
