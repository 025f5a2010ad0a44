"""SMPL-family linear blend skinning in PyTorch (batched, differentiable).

Conventions (identical to the official MANO / FLAME / SMPL code):

* ``v_shaped = v_template + shapedirs . betas``
* ``J = J_regressor @ v_shaped`` (rest joints)
* ``pose_feature = concat_j>=1 (R_j - I).flatten()`` (9 (J - 1) numbers)
* ``v_posed = v_shaped + posedirs . pose_feature``
* forward kinematics along ``parents``: ``G_j = G_parent(j) [R_j | J_j - J_parent(j)]``
* ``v = sum_j w_j G_j (v_posed - J_j)`` (the rest-joint offset removed).

Every function keeps the dtype and device of its inputs.
"""

from __future__ import annotations

import torch

# Below this squared angle the Rodrigues coefficients use their Taylor series;
# the truncation error (theta^6 / 5040) is then below float64 round-off.
_SMALL_ANGLE_SQ = 1e-4


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]_x."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), dim=-1).reshape(*v.shape[:-1], 3, 3)


def batch_rodrigues(rotvec: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors (..., 3) -> rotation matrices (..., 3, 3).

    ``R = I + A(theta) K + B(theta) K^2`` with ``K = [r]_x`` (unnormalised),
    ``A = sin(theta)/theta`` and ``B = (1 - cos(theta))/theta^2``.  Near zero
    both coefficients switch to their Taylor series through a "double where",
    so neither the value nor the gradient is NaN at exactly zero.
    """
    if rotvec.shape[-1] != 3:
        raise ValueError(f"batch_rodrigues expects (..., 3) axis-angle vectors, got {tuple(rotvec.shape)}")
    theta_sq = (rotvec * rotvec).sum(-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = torch.sqrt(safe_sq)
    half_sin = torch.sin(0.5 * theta)
    a_big = torch.sin(theta) / theta
    b_big = 2.0 * half_sin * half_sin / safe_sq
    a_small = 1.0 - theta_sq / 6.0 + theta_sq * theta_sq / 120.0
    b_small = 0.5 - theta_sq / 24.0 + theta_sq * theta_sq / 720.0
    a = torch.where(small, a_small, a_big)[..., None, None]
    b = torch.where(small, b_small, b_big)[..., None, None]
    k = _skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """betas (B, S), shapedirs (V, 3, S) -> per-vertex offsets (B, V, 3)."""
    return torch.einsum("bs,vcs->bvc", betas, shapedirs)


def pose_feature(rot_mats: torch.Tensor) -> torch.Tensor:
    """(B, J, 3, 3) local rotations -> (B, 9 (J - 1)) pose-corrective feature."""
    eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
    return (rot_mats[:, 1:] - eye).reshape(rot_mats.shape[0], -1)


def batch_rigid_transform(
    rot_mats: torch.Tensor, joints: torch.Tensor, parents: list[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics.

    Args:
        rot_mats: (B, J, 3, 3) local joint rotations.
        joints: (B, J, 3) rest joint locations.
        parents: J parent indices, ``parents[0] == -1`` and ``parents[j] < j``.

    Returns:
        posed_joints (B, J, 3) and the skinning transforms (B, J, 4, 4) that map
        a rest-pose point to its posed location (rest-joint offset removed).
    """
    rotations: list[torch.Tensor] = []
    translations: list[torch.Tensor] = []
    for j, parent in enumerate(parents):
        if parent < 0:
            rotations.append(rot_mats[:, j])
            translations.append(joints[:, j])
            continue
        offset = joints[:, j] - joints[:, parent]
        rotations.append(rotations[parent] @ rot_mats[:, j])
        translations.append(translations[parent] + (rotations[parent] @ offset[..., None])[..., 0])
    rot = torch.stack(rotations, dim=1)
    posed_joints = torch.stack(translations, dim=1)
    trans = posed_joints - (rot @ joints[..., None])[..., 0]
    bottom = torch.zeros(*rot.shape[:2], 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1.0
    transforms = torch.cat((torch.cat((rot, trans[..., None]), dim=-1), bottom), dim=-2)
    return posed_joints, transforms


def lbs(
    betas: torch.Tensor,
    pose: torch.Tensor,
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor,
    J_regressor: torch.Tensor,
    parents: list[int],
    weights: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear blend skinning.

    Args:
        betas: (B, S) shape (and expression) coefficients.
        pose: (B, J, 3) axis-angle local rotations, or (B, J, 3, 3) matrices.
        v_template: (V, 3); shapedirs: (V, 3, S); posedirs: (V, 3, 9 (J - 1));
        J_regressor: (J, V); weights: (V, J).
        parents: J parent indices (root -1).

    Returns:
        vertices (B, V, 3) and posed joints (B, J, 3), without translation.
    """
    rot_mats = pose if pose.ndim == 4 else batch_rodrigues(pose)
    v_shaped = v_template + blend_shapes(betas, shapedirs)
    joints = torch.einsum("jv,bvc->bjc", J_regressor, v_shaped)
    v_posed = v_shaped + torch.einsum("bp,vcp->bvc", pose_feature(rot_mats), posedirs)
    posed_joints, transforms = batch_rigid_transform(rot_mats, joints, parents)
    per_vertex = torch.einsum("vj,bjmn->bvmn", weights, transforms)
    vertices = (per_vertex[..., :3, :3] @ v_posed[..., None])[..., 0] + per_vertex[..., :3, 3]
    return vertices, posed_joints
