"""DECAF's FLAME/MANO parameter conventions -> this project's (:class:`FLAMELayer`, :class:`MANOLayer`).

DECAF (Shimada et al. 2023; its public ``FLAME_util.flame_forwarding`` and
``tracking_util.rigid_transform_with_scaling``) poses the head in two steps:

1. FLAME with ``pose_params`` = root (3) then jaw (3) axis-angle, neck and eyes zero, no translation:
   mesh ``v_F``; the root rotation ``R_r`` turns the mesh about the root joint ``J0``;
2. a rigid transform about the *centroid* ``c`` of ``v_F``:  ``v = R_g (v_F - c) + c + t``
   with ``R_g`` from ``global_orient`` and ``t`` = ``transl`` (scale 1).

:class:`FLAMELayer` turns the whole mesh about ``J0`` and adds ``transl``. With ``u`` the mesh of
step 1 without root rotation (``v_F = R_r (u - J0) + J0``) and ``u_bar`` its centroid, the same
vertices come out of our layer with

    global_orient = log(R_g R_r),    transl = t + (R_g - I) R_r (J0 - u_bar).

``J0`` and ``u_bar`` depend on the shape, expression and jaw of every frame, so the conversion runs
the FLAME model: it needs the official FLAME 2020 file (DECAF's parameters index its 100 identity
and 50 expression components). MANO needs no conversion: DECAF's MANO (45 axis-angle values, flat
hand mean, rotation about the wrist joint, translation added) is :class:`MANOLayer`'s convention;
its ``betas`` still only mean something on the official MANO model. (A caution: the MANO package
DECAF's scripts load, github.com/otaheri/MANO, skins with the module's own zero ``betas`` rather
than the ones passed to ``forward`` in the version read for this adapter, so those scripts draw the
hand with the mean shape; the betas are imported as shipped.)

DECAF's ``deforms.npy`` are FLAME-canonical offsets that its scripts rotate by ``R_g`` and
subtract from the posed head; :func:`decaf_world_offsets` turns them into this project's
world-frame offsets that are added.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar.templates.layers import FLAMELayer
from avatar.templates.model import TemplateModel

CHUNK = 128  # frames per FLAME evaluation: bounds memory on long sequences


def _flame_rest_points(
    head: TemplateModel, shape: np.ndarray, expression: np.ndarray, jaw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Root joint J0 (T, 3) and vertex centroid (T, 3) of the unrotated, untranslated FLAME mesh."""
    layer = FLAMELayer(head, num_shape=shape.shape[1], num_expression=expression.shape[1])
    root, centroid = [], []
    with torch.no_grad():
        for start in range(0, len(shape), CHUNK):
            part = slice(start, start + CHUNK)
            out = layer(
                torch.from_numpy(shape[part]), torch.from_numpy(expression[part]), jaw_pose=torch.from_numpy(jaw[part])
            )
            root.append(out.joints[:, 0].numpy())
            centroid.append(out.vertices.mean(dim=1).numpy())
    return np.concatenate(root), np.concatenate(centroid)


def decaf_head_to_flame(
    head: TemplateModel,
    shape: np.ndarray,
    expression: np.ndarray,
    pose: np.ndarray,
    global_orient: np.ndarray,
    transl: np.ndarray,
) -> dict[str, np.ndarray]:
    """DECAF head parameters (T rows each; ``pose`` (T, 6) = root, jaw) -> the ``flame_*`` columns of
    ``params.parquet``. Raises ValueError when the widths do not fit ``head``."""
    num_expr = head.num_shapes_total - head.num_identity_shape
    if shape.shape[1] > head.num_identity_shape or expression.shape[1] > num_expr:
        raise ValueError(
            f"{shape.shape[1]} shape and {expression.shape[1]} expression coefficients do not fit a "
            f"head model with {head.num_shape} and {num_expr}; DECAF's parameters need the official "
            f"FLAME 2020 generic_model.pkl (model.flame_path)"
        )
    f64 = {
        k: np.asarray(v, dtype=np.float64)
        for k, v in dict(
            shape=shape, expression=expression, pose=pose, global_orient=global_orient, transl=transl
        ).items()
    }
    joint0, centroid = _flame_rest_points(head, f64["shape"], f64["expression"], f64["pose"][:, 3:])
    R_r = Rotation.from_rotvec(f64["pose"][:, :3]).as_matrix()
    R_g = Rotation.from_rotvec(f64["global_orient"]).as_matrix()
    lever = np.einsum("tij,tj->ti", R_r, joint0 - centroid)
    transl_ours = f64["transl"] + np.einsum("tij,tj->ti", R_g, lever) - lever
    n = len(shape)
    return {
        "flame_shape": f64["shape"],
        "flame_expression": f64["expression"],
        "flame_global_orient": Rotation.from_matrix(R_g @ R_r).as_rotvec(),
        "flame_neck_pose": np.zeros((n, 3)),
        "flame_jaw_pose": f64["pose"][:, 3:],
        "flame_eye_pose": np.zeros((n, 6)),
        "flame_transl": transl_ours,
    }


def decaf_hand_to_mano(
    hand: TemplateModel, betas: np.ndarray, hand_pose: np.ndarray, global_orient: np.ndarray, transl: np.ndarray
) -> dict[str, np.ndarray]:
    """DECAF right-hand parameters -> the ``mano_*`` columns (same convention; widths checked)."""
    if betas.shape[1] != hand.num_shapes_total or hand_pose.shape[1] != 45:
        raise ValueError(
            f"{betas.shape[1]} betas and {hand_pose.shape[1]} pose values do not fit a hand model "
            f"with {hand.num_shapes_total} shape components and 45 pose values; DECAF's parameters "
            f"need the official MANO_RIGHT.pkl (model.mano_path)"
        )
    as64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    return {
        "mano_shape": as64(betas),
        "mano_hand_pose": as64(hand_pose),
        "mano_global_orient": as64(global_orient),
        "mano_transl": as64(transl),
    }


def decaf_world_offsets(deforms: np.ndarray, global_orient: np.ndarray) -> np.ndarray:
    """DECAF canonical deformations (T, V, 3), subtracted after rotating by the head ``global_orient``
    (T, 3) -> world-frame offsets (T, V, 3) added to the posed face mesh."""
    R_g = Rotation.from_rotvec(np.asarray(global_orient, dtype=np.float64)).as_matrix()
    return -np.einsum("tij,tvj->tvi", R_g, np.asarray(deforms, dtype=np.float64))
