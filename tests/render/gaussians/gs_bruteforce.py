"""An independent brute-force Gaussian renderer for the rasterizer tests: every Gaussian at every pixel.

Same 3DGS maths as the rasterizer (EWA projection with the Jacobian's x/z, y/z clamped to the
image plus 0.3 of the half field of view, 0.3 low-pass, alpha = min(0.99, o exp(-m/2)) skipped
below 1/255, front-to-back compositing stopping before T < 1e-4), written with full matrices,
one global depth sort and no tiles, no boxes, no culling except the near/far planes.
Differentiable by plain autograd. Memory is O(N H W): tiny scenes only.
"""

from __future__ import annotations

import torch
from torch import Tensor


def rotation(quats: Tensor) -> Tensor:
    """(N, 3, 3) from wxyz quaternions: R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x on the unit quaternion."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[:, :1, None], q[:, 1:]
    cross = torch.zeros(q.shape[0], 3, 3, dtype=q.dtype)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    cross = cross - cross.transpose(1, 2)
    eye = torch.eye(3, dtype=q.dtype).expand_as(cross)
    return (w * w - (v * v).sum(-1)[:, None, None]) * eye + 2 * v[:, :, None] * v[:, None, :] + 2 * w * cross


def project(
    means: Tensor, quats: Tensor, scales: Tensor, K: Tensor, world_to_cam: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor, Tensor]:
    """2D means (N, 2), 2D covariances (N, 2, 2) with the low-pass, camera z (N,)."""
    rot_wc, t_wc = world_to_cam[:3, :3], world_to_cam[:3, 3]
    p = means @ rot_wc.T + t_wc
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    lim_x_neg = (cx + 0.5) / fx + 0.15 * width / fx
    lim_x_pos = (width - 0.5 - cx) / fx + 0.15 * width / fx
    lim_y_neg = (cy + 0.5) / fy + 0.15 * height / fy
    lim_y_pos = (height - 0.5 - cy) / fy + 0.15 * height / fy
    tx = torch.maximum(torch.minimum(x / z, lim_x_pos), -lim_x_neg) * z
    ty = torch.maximum(torch.minimum(y / z, lim_y_pos), -lim_y_neg) * z
    jac = torch.zeros(means.shape[0], 2, 3, dtype=means.dtype)
    jac[:, 0, 0], jac[:, 0, 2] = fx / z, -fx * tx / (z * z)
    jac[:, 1, 1], jac[:, 1, 2] = fy / z, -fy * ty / (z * z)
    r = rotation(quats)
    cov3d = r @ torch.diag_embed(scales * scales) @ r.transpose(1, 2)
    t = jac @ rot_wc
    cov2d = t @ cov3d @ t.transpose(1, 2) + 0.3 * torch.eye(2, dtype=means.dtype)
    return means2d, cov2d, z


def composite(
    means2d: Tensor,
    cov2d: Tensor,
    depths: Tensor,
    opacities: Tensor,
    colors: Tensor,
    width: int,
    height: int,
    background: Tensor,
    valid: Tensor,
) -> dict[str, Tensor]:
    """Brute-force front-to-back compositing of 2D Gaussians; ``valid`` (N,) masks culled ones.

    Returns rgb (H, W, 3), alpha (H, W), depth (H, W) and stopped (H, W): whether the early stop
    dropped a Gaussian at the pixel.
    """
    order = torch.argsort(depths.detach(), stable=True)
    order = order[valid[order]]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype), torch.arange(width, dtype=means2d.dtype), indexing="ij"
    )
    pix = torch.stack([xs, ys], -1)  # (H, W, 2), OpenCV centres
    d = pix[None] - means2d[order][:, None, None, :]  # (M, H, W, 2)
    conic = torch.linalg.inv(cov2d[order])
    maha = torch.einsum("nhwi,nij,nhwj->nhw", d, conic, d)
    alpha = (opacities[order][:, None, None] * torch.exp(-0.5 * maha)).clamp_max(0.99)
    alpha = alpha * (alpha >= 1.0 / 255.0)
    trans_after = torch.cumprod(1 - alpha, 0)
    trans_before = torch.cat([torch.ones_like(alpha[:1]), trans_after[:-1]])
    kept = trans_after >= 1e-4
    w = alpha * trans_before * kept
    acc = w.sum(0)
    rgb = torch.einsum("nhw,nc->hwc", w, colors[order]) + (1 - acc)[..., None] * background
    depth = torch.einsum("nhw,n->hw", w, depths[order])
    stopped = ((alpha > 0) & ~kept).any(0)
    return {"rgb": rgb, "alpha": acc, "depth": depth, "stopped": stopped}


def render(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    width: int,
    height: int,
    background: Tensor,
    near: float = 0.01,
    far: float = 100.0,
) -> dict[str, Tensor]:
    """rgb (H, W, 3), alpha (H, W), depth (H, W), stopped (H, W) and means2d (N, 2) of the scene."""
    means2d, cov2d, z = project(means, quats, scales, K, world_to_cam, width, height)
    valid = (z >= near) & (z <= far)
    out = composite(means2d, cov2d, z, opacities, colors, width, height, background, valid)
    out["means2d"] = means2d
    return out
