"""Motion transfer: the driver's performance on the target's identity.

The target keeps its own FLAME and MANO shape. From the driver it takes, per frame, the face pose (global
orientation, neck, jaw, eyes), the expression and the finger pose. Placement:

- head: the target's head root joint follows the driver's root trajectory relative to the driver's first
  frame, starting from the target's own first-frame root (so the target stays where its cameras look);
- hand, scaled (``placement="scaled"``, and the start of ``"contact"``): the driver's hand-to-head transform
  is kept: the hand's anatomical frame (:func:`avatar.templates.layers.hand_frame`: wrist to middle knuckle,
  palm normal) relative to
  the head exactly, and ``t_rel = R_head^T (wrist - head_root)`` scaled by the ratio of the heads' sizes
  (:func:`head_size`). The finger rotations are turned by the same change of frame, so a finger flexes about
  the target's own knuckle axes. When both hands share a shape, this is the driver's MANO orientation and pose;
- hand, contact-preserving (``placement="contact"``, the default): then each frame whose hand comes within the
  interaction radius of the driver's face is corrected by one rigid motion that puts the points touching the
  driver's face on the same surface points of the target's face (:mod:`avatar.reenact.contact`), fading to
  the scaled placement as the hand leaves the face.

FLAME and MANO rotate about their root joint, so a root joint's posed position is its rest position plus
the translation; the new translations are solved from that (and checked by the tests by posing again).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar.posing import pose_layers
from avatar.reenact.contact import PASS_THROUGH_M, place_hand
from avatar.templates import MANOLayer, TemplateModel
from avatar.templates.layers import hand_frame
from avatar.templates.lbs import batch_rodrigues
from data_schemas.params import PARAMS

#: The largest magnitude a parameter may have: a kilometre from the world's origin, a thousand radians, a thousand
#: shape or expression units. No capture comes near it, and beyond it the float32 posing rounds a head to a point.
PARAMETER_LIMIT = 1e3
#: the unit of each parameter column (params.parquet's schema), for the messages
PARAMETER_UNITS = {c.name: c.unit for c in PARAMS.columns if c.unit}
#: what the driver gives, per frame
DRIVER_COLUMNS = (
    "flame_expression",
    "flame_global_orient",
    "flame_neck_pose",
    "flame_jaw_pose",
    "flame_eye_pose",
    "mano_hand_pose",
    "mano_global_orient",
)


PLACEMENTS = ("contact", "scaled")


class MotionTransferError(ValueError):
    """The driver's parameters cannot drive the target (another template, NaN, an empty sequence)."""


class MotionTransfer(NamedTuple):
    """The target performing the driver's motion: ``params`` (T rows, the columns of ``params.parquet``), the
    head-size ratio target / driver ``head_scale``, and per frame how the hand was placed (``frames``: the hand
    vertices matched to the driver's face, touching it, and of those touching the target's face too (kept); the
    touching points' residual distance from the same surface points; the correction's size; empty for the
    scaled placement)."""

    params: dict[str, np.ndarray]
    head_scale: float
    frames: list[dict]


def head_size(face_vertices: np.ndarray) -> float:
    """RMS distance of the face vertices (V, 3) to their centroid, metres: a rotation-invariant head size."""
    centred = face_vertices - face_vertices.mean(0)
    return float(np.sqrt((centred**2).sum(-1).mean()))


def _rest_joints(shape: np.ndarray, hand: TemplateModel) -> np.ndarray:
    """(16, 3) joints of the hand ``shape`` (1, B) in its rest pose."""
    t = torch.from_numpy(np.asarray(shape, np.float64))
    zeros = torch.zeros(1, 3, dtype=torch.float64)
    with torch.no_grad():
        return MANOLayer(hand)(t, torch.zeros(1, 45, dtype=torch.float64), zeros, zeros).joints[0].numpy()


def transfer_motion(
    target: Mapping[str, np.ndarray],
    driver: Mapping[str, np.ndarray],
    head: TemplateModel,
    hand: TemplateModel,
    placement: str = "contact",
) -> MotionTransfer:
    """The target performing the driver's motion (module docstring).

    Args:
        target: the target's fitted parameters (any number of frames; shapes averaged over them).
        driver: the driver's parameters, one row per output frame.
        head, hand: the templates both were fitted with.
        placement: ``contact`` (keep the driver's touches on the same surface points) or ``scaled``.
    Raises:
        MotionTransferError: empty driver, non-finite parameters, or widths that do not match (another template).
    """
    if placement not in PLACEMENTS:
        raise ValueError(f"placement={placement!r}: use one of {PLACEMENTS}")
    _check(target, driver)
    T = len(driver["flame_global_orient"])
    out = {k: np.array(driver[k], dtype=np.float64) for k in DRIVER_COLUMNS}
    for name in ("flame_shape", "mano_shape"):
        out[name] = np.repeat(np.asarray(target[name], np.float64).mean(0, keepdims=True), T, axis=0)
    change = (
        hand_frame(_rest_joints(out["mano_shape"][:1], hand))
        @ hand_frame(_rest_joints(np.asarray(driver["mano_shape"], np.float64)[:1], hand)).T
    )
    out["mano_hand_pose"] = np.einsum("ij,tkj->tki", change, out["mano_hand_pose"].reshape(T, -1, 3)).reshape(T, -1)
    R_driver = batch_rodrigues(torch.from_numpy(out["mano_global_orient"])).numpy()
    out["mano_global_orient"] = _rotvec(R_driver @ change.T)
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
    if placement == "scaled":
        return MotionTransfer(out, scale, [])
    return MotionTransfer(out, scale, _keep_contacts(out, driver_pose, head, hand, hand0.joints[:, 0].numpy()))


def _rotvec(matrices: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle vectors of rotation matrices (T, 3, 3)."""
    return Rotation.from_matrix(matrices).as_rotvec()


def _keep_contacts(
    out: dict[str, np.ndarray], driver_pose: tuple, head: TemplateModel, hand: TemplateModel, rest_wrist: np.ndarray
) -> list[dict]:
    """Correct ``out``'s hand placement in place, frame by frame (:func:`avatar.reenact.contact.place_hand`);
    the per-frame report. ``rest_wrist`` (T, 3): the target hand's root joint with zero translation."""
    _, face, _, hand_now = pose_layers(out, head, hand, torch.float64)
    faces = np.asarray(head.faces, dtype=np.int64)
    R_hand = batch_rodrigues(torch.from_numpy(out["mano_global_orient"])).numpy()
    report, through = [], []
    for t in range(len(R_hand)):
        fix = place_hand(
            driver_pose[3].vertices[t].numpy(),
            driver_pose[1].vertices[t].numpy(),
            hand_now.vertices[t].numpy(),
            face.vertices[t].numpy(),
            faces,
        )
        wrist = hand_now.joints[t, 0].numpy()
        if fix.matched:  # else exactly the scaled placement
            wrist = fix.rotation @ wrist + fix.translation
            out["mano_global_orient"][t] = _rotvec((fix.rotation @ R_hand[t])[None])[0]
            out["mano_transl"][t] = wrist - rest_wrist[t]
        if fix.driver_depth_m > PASS_THROUGH_M:
            through.append(t)
        report.append(
            {
                "frame": t,
                "matched_points": fix.matched,
                "touching_points": fix.touching,
                "kept_points": fix.kept,
                "residual_mm": 1e3 * fix.residual_m,
                "moved_mm": 1e3 * float(np.linalg.norm(wrist - hand_now.joints[t, 0].numpy())),
                "turned_deg": float(np.degrees(np.linalg.norm(_rotvec(fix.rotation[None])))),
                "driver_depth_mm": 1e3 * fix.driver_depth_m,
            }
        )
    if through:
        warnings.warn(
            f"motion transfer: in driver frames {through[:10]} the hand lies more than "
            f"{PASS_THROUGH_M * 1e3:.0f} mm inside the driver's own face (up to "
            f"{max(report[t]['driver_depth_mm'] for t in through):.0f} mm): its fit passes through the "
            f"face; those touches are transferred as they are",
            stacklevel=3,
        )
    return report


def parameter_problem(params: Mapping[str, np.ndarray], name: str = "driver") -> str | None:
    """Why the parameters ``params`` (params.parquet's columns, a row per frame) cannot be posed, naming the column,
    the first frames and the fix, or ``None``: a value that is not finite, or one beyond :data:`PARAMETER_LIMIT`."""
    fix = "fix or drop those frames' parameters"
    for key, value in params.items():
        rows = np.abs(np.asarray(value, np.float64).reshape(len(value), -1))
        unfinite = np.flatnonzero(~np.isfinite(rows).all(1))
        if unfinite.size:
            return f"the {name}'s '{key}' is not finite in frames {unfinite[:5].tolist()}; {fix}"
        beyond = np.flatnonzero(rows.max(1, initial=0.0) > PARAMETER_LIMIT)
        if beyond.size:
            unit = f" {PARAMETER_UNITS[key]}" if key in PARAMETER_UNITS else ""
            return (
                f"the {name}'s '{key}' reaches {rows.max():.3g}{unit} in frames {beyond[:5].tolist()}: beyond "
                f"{PARAMETER_LIMIT:g}{unit}, which no capture reaches and where posing rounds a head to a point; {fix}"
            )
    return None


def _check(target: Mapping[str, np.ndarray], driver: Mapping[str, np.ndarray]) -> None:
    if len(driver.get("flame_global_orient", ())) == 0:
        raise MotionTransferError("the driver sequence has no frames")
    for name, params in (("driver", driver), ("target", target)):
        problem = parameter_problem(params, name)
        if problem is not None:
            raise MotionTransferError(problem)
    for key in ("flame_shape", "flame_expression", "mano_shape", "mano_hand_pose"):
        wd, wt = np.asarray(driver[key]).shape[1:], np.asarray(target[key]).shape[1:]
        if wd != wt:
            raise MotionTransferError(
                f"'{key}' has width {wd} in the driver and {wt} in the target: they were fitted "
                f"with different templates; fit both with the same model files"
            )
