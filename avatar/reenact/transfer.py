"""Motion transfer: the driver's performance on the target's identity.

The target keeps its own FLAME and MANO shape. From the driver it takes, per frame, the face pose (global
orientation, neck, jaw, eyes), the expression and the finger pose. Placement:

- head: the target's head root joint follows the driver's root trajectory relative to the driver's first
  frame, starting from the target's own first-frame root (so the target stays where its cameras look);
- hand: the driver's hand-to-head transform is kept, ``R_rel = R_head^T R_hand`` exactly and
  ``t_rel = R_head^T (wrist - head_root)`` scaled by the ratio of the heads' sizes (:func:`head_size`), so a
  hand pressing the driver's cheek presses the target's cheek.

FLAME and MANO rotate about their root joint, so a root joint's posed position is its rest position plus
the translation; the new translations are solved from that (and checked by the tests by posing again).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from avatar.templates import TemplateModel
from avatar.templates.lbs import batch_rodrigues
from avatar.training.posing import pose_layers

#: what the driver gives, per frame
DRIVER_COLUMNS = ("flame_expression", "flame_global_orient", "flame_neck_pose", "flame_jaw_pose", "flame_eye_pose",
                  "mano_hand_pose", "mano_global_orient")


class MotionTransferError(ValueError):
    """The driver's parameters cannot drive the target (another template, NaN, an empty sequence)."""


def head_size(face_vertices: np.ndarray) -> float:
    """RMS distance of the face vertices (V, 3) to their centroid, metres: a rotation-invariant head size."""
    centred = face_vertices - face_vertices.mean(0)
    return float(np.sqrt((centred ** 2).sum(-1).mean()))


def transfer_motion(target: Mapping[str, np.ndarray], driver: Mapping[str, np.ndarray], head: TemplateModel,
                    hand: TemplateModel) -> tuple[dict[str, np.ndarray], float]:
    """Parameters (T_driver rows, the columns of ``params.parquet``) of the target performing the driver's motion,
    and the head-size ratio target / driver used for the hand placement.

    Args:
        target: the target's fitted parameters (any number of frames; shapes averaged over them).
        driver: the driver's parameters, one row per output frame.
        head, hand: the templates both were fitted with.
    Raises:
        MotionTransferError: empty driver, non-finite parameters, or widths that do not match (another template).
    """
    _check(target, driver)
    T = len(driver["flame_global_orient"])
    out = {k: np.array(driver[k], dtype=np.float64) for k in DRIVER_COLUMNS}
    for name in ("flame_shape", "mano_shape"):
        out[name] = np.repeat(np.asarray(target[name], np.float64).mean(0, keepdims=True), T, axis=0)
    # Rest root joints of the target's shapes: pose once with zero translations.
    out["flame_transl"] = np.zeros((T, 3))
    out["mano_transl"] = np.zeros((T, 3))
    _, face0, _, hand0 = pose_layers(out, head, hand, torch.float64)
    driver_pose = pose_layers(dict(driver), head, hand, torch.float64)
    target_pose = pose_layers({k: np.asarray(v)[:1] for k, v in target.items()}, head, hand, torch.float64)
    d_root, d_wrist = driver_pose[1].joints[:, 0].numpy(), driver_pose[3].joints[:, 0].numpy()
    t_root0 = target_pose[1].joints[0, 0].numpy()
    scale = head_size(target_pose[1].vertices[0].numpy()) / head_size(driver_pose[1].vertices[0].numpy())
    root = t_root0 + (d_root - d_root[0])
    out["flame_transl"] = root - face0.joints[:, 0].numpy()
    R_head = batch_rodrigues(torch.from_numpy(out["flame_global_orient"])).numpy()
    t_rel = np.einsum("tji,tj->ti", R_head, d_wrist - d_root)  # R_head^T (wrist - root), driver's frame
    wrist = root + scale * np.einsum("tij,tj->ti", R_head, t_rel)
    out["mano_transl"] = wrist - hand0.joints[:, 0].numpy()
    return out, scale


def _check(target: Mapping[str, np.ndarray], driver: Mapping[str, np.ndarray]) -> None:
    if len(driver.get("flame_global_orient", ())) == 0:
        raise MotionTransferError("the driver sequence has no frames")
    for name, params in (("driver", driver), ("target", target)):
        for key, value in params.items():
            rows = np.asarray(value, np.float64).reshape(len(value), -1)
            bad = np.flatnonzero(~np.isfinite(rows).all(1))
            if bad.size:
                raise MotionTransferError(f"the {name}'s '{key}' is not finite in frames {bad[:5].tolist()}; fix or "
                                          f"drop those frames' parameters")
    for key in ("flame_shape", "flame_expression", "mano_shape", "mano_hand_pose"):
        wd, wt = np.asarray(driver[key]).shape[1:], np.asarray(target[key]).shape[1:]
        if wd != wt:
            raise MotionTransferError(f"'{key}' has width {wd} in the driver and {wt} in the target: they were fitted "
                                      f"with different templates; fit both with the same model files")
