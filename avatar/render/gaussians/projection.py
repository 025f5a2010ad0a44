"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (3DGS maths).

Conventions: OpenCV camera axes (x right, y down, z forward) and OpenCV pixel
coordinates, in which pixel ``(row i, col j)`` has its centre at ``(x, y) = (j, i)``.
A camera-space point ``(x, y, z)`` projects to ``(fx x / z + cx, fy y / z + cy)``.

All per-Gaussian maths runs in float64 (it is O(N), hence cheap) so that huge
scales, near-plane depths and near-singular covariances cannot overflow; the
differentiable results are cast back to the input dtype.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import torch
from torch import Tensor

#: Variance (pixels^2) added to the diagonal of every 2D covariance (3DGS low-pass filter).
LOW_PASS = 0.3
#: Compositing skips a Gaussian at a pixel where its alpha is below this value.
ALPHA_MIN = 1.0 / 255.0
#: The EWA Jacobian clamps x/z and y/z this fraction of the half field of view past the image.
FOV_MARGIN = 0.3
_QUAT_EPS2 = 1e-24
_MAX_RADIUS = 2.0**30


@dataclass
class Projection:
    """Screen-space Gaussians, one row per input Gaussian (culled ones have ``visible == False``).

    Attributes:
        means2d: (N, 2) projected centres in OpenCV pixel coordinates (differentiable).
        conics: (N, 3) inverse 2D covariance ``(a, b, c)`` of ``[[a, b], [b, c]]`` (differentiable).
        depths: (N,) camera-space z (differentiable; 1 where culled by depth).
        box: (N, 4) int64 ``(x0, y0, x1, y1)`` inclusive pixel box, clipped to the image, outside
            of which the Gaussian's alpha is below ``ALPHA_MIN`` (meaningless where culled).
        visible: (N,) bool: depth within ``[near, far]``, opacity above ``ALPHA_MIN`` and at
            least one pixel centre in the box.
        radii: (N,) int32 pixel radius, ``ceil`` of the larger box half-width, 0 where culled.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    box: Tensor
    visible: Tensor
    radii: Tensor


def _columns(x: Tensor) -> list[Tensor]:
    """(N, k) -> k contiguous float64 (N,) columns (the maths below is per component: small-matrix
    batched ops and reductions over size-3 axes are several times slower on the CPU)."""
    return list(x.to(torch.float64).T.contiguous().unbind(0))


def rotation_entries(quats: Tensor) -> list[list[Tensor]]:
    """Rotation matrix entries ``R[i][j]`` (each (N,) float64) of wxyz quaternions (N, 4), normalised here.

    A zero quaternion maps to the identity, with finite gradients.
    """
    w, x, y, z = _columns(quats)
    inv_norm = torch.rsqrt((w * w + x * x + y * y + z * z).clamp_min(_QUAT_EPS2))
    w, x, y, z = w * inv_norm, x * inv_norm, y * inv_norm, z * inv_norm
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def fov_limits(K: Tensor, width: int, height: int) -> tuple[float, float, float, float]:
    """Clamping limits ``(x_neg, x_pos, y_neg, y_pos)`` of ``x/z`` and ``y/z`` in the EWA Jacobian.

    Each side of the principal point extends to the image border plus ``FOV_MARGIN`` of the
    half field of view: 3DGS's ``1.3 tan(fov / 2)`` for a centred principal point, gsplat's
    asymmetric form otherwise. The image spans ``[-0.5, W - 0.5]`` in OpenCV coordinates.
    """
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    margin_x = FOV_MARGIN * 0.5 * width / fx
    margin_y = FOV_MARGIN * 0.5 * height / fy
    return (
        (cx + 0.5) / fx + margin_x,
        (width - 0.5 - cx) / fx + margin_x,
        (cy + 0.5) / fy + margin_y,
        (height - 0.5 - cy) / fy + margin_y,
    )


def alpha_extent(opacities: Tensor) -> Tensor:
    """Mahalanobis radius (N,) float64 beyond which ``opacity * exp(-r^2 / 2) < ALPHA_MIN``.

    ``sqrt(2 ln(opacity / ALPHA_MIN))`` is at most 3.33 (opacity 1): the opacity-aware bound of
    gsplat >= 1.5, 0 where the opacity is at most ``ALPHA_MIN``. Culling tiles with it drops only
    pixels that compositing skips anyway, so the tiled image equals the brute-force one.
    """
    ratio = (opacities.detach().double() / ALPHA_MIN).clamp_min(1.0)
    return torch.sqrt(2.0 * torch.log(ratio))


def _image_jacobian(
    p_cam: list[Tensor], rot_wc: list[list[float]], K: Tensor, width: int, height: int
) -> list[list[Tensor]]:
    """Rows of the EWA Jacobian of the projection composed with the camera rotation, ``J W`` (2 x 3 of (N,)).

    ``J = [[fx / z, 0, -fx tx / z], [0, fy / z, -fy ty / z]]`` with ``tx = x / z`` and ``ty = y / z``
    clamped to ``fov_limits``, so row ``i`` of ``J W`` is ``f_i / z (W_i - t_i W_2)``.
    """
    x_neg, x_pos, y_neg, y_pos = fov_limits(K, width, height)
    x, y, z = p_cam
    rows = []
    for axis, (f, t) in enumerate(
        ((float(K[0, 0]), (x / z).clamp(-x_neg, x_pos)), (float(K[1, 1]), (y / z).clamp(-y_neg, y_pos)))
    ):
        f_z = f / z
        rows.append([f_z * (rot_wc[axis][k] - t * rot_wc[2][k]) for k in range(3)])
    return rows


def _pixel_box(means2d: Tensor, half: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Inclusive pixel box (N, 4) int64 of the centres within ``half`` (N, 2), and whether it is non-empty."""
    lo = (means2d - half).ceil()
    hi = (means2d + half).floor()
    size = means2d.new_tensor([width - 1.0, height - 1.0])
    lo_c = torch.minimum(lo.clamp_min(0.0), size)
    hi_c = torch.minimum(hi.clamp_min(0.0), size)
    nonempty = ((lo <= hi) & (hi >= 0) & (lo <= size)).all(-1)
    return torch.cat([lo_c, hi_c], -1).long(), nonempty


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
) -> Projection:
    """Project N 3D Gaussians with the EWA approximation.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations, any norm (zero gives the identity).
        scales: (N, 3) linear standard deviations along the rotated axes.
        opacities: (N,) in [0, 1] (only used for culling and the alpha extent).
        K: (3, 3) OpenCV intrinsics.
        world_to_cam: (4, 4) rigid world-to-camera transform.
        width, height: image size in pixels.
        near, far: Gaussians with camera z outside ``[near, far]`` are culled.
    """
    dtype = means.dtype
    view = world_to_cam.detach().to(torch.float64)
    p_cam = means.to(torch.float64) @ view[:3, :3].T + view[:3, 3]
    in_depth = (p_cam[:, 2] >= near) & (p_cam[:, 2] <= far) & torch.isfinite(p_cam).all(-1)
    # Culled Gaussians get a safe point at z = 1 so that nothing below divides by ~0.
    p_cam = torch.where(in_depth[:, None], p_cam, p_cam.new_tensor([0.0, 0.0, 1.0]))
    x, y, z = _columns(p_cam)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)

    jw = _image_jacobian([x, y, z], view[:3, :3].tolist(), K, width, height)
    rot = rotation_entries(quats)
    scale = _columns(scales)
    # 2D covariance = A A^T with A = J W R diag(s).
    a_mat = [[sum(jw[i][k] * rot[k][j] for k in range(3)) * scale[j] for j in range(3)] for i in range(2)]
    # cast: sum() starts from the int 0, which the first (N,) term turns into a tensor
    a = cast(Tensor, sum(v * v for v in a_mat[0])) + LOW_PASS
    b = cast(Tensor, sum(u * v for u, v in zip(a_mat[0], a_mat[1])))
    c = cast(Tensor, sum(v * v for v in a_mat[1])) + LOW_PASS
    finite = torch.isfinite(a) & torch.isfinite(b) & torch.isfinite(c)  # only fails past ~1e150
    a, b, c = (torch.where(finite, v, torch.full_like(v, fill)) for v, fill in ((a, LOW_PASS), (b, 0.0), (c, LOW_PASS)))
    det = a * c - b * b  # >= LOW_PASS^2 since A A^T is positive semi-definite
    conics = torch.stack([c / det, -b / det, a / det], -1)

    with torch.no_grad():
        extent = alpha_extent(opacities)
        half = extent[:, None] * torch.stack([a, c], -1).sqrt()
        box, nonempty = _pixel_box(means2d, half.clamp_max(_MAX_RADIUS), width, height)
        visible = in_depth & finite & (extent > 0) & nonempty & torch.isfinite(means2d).all(-1)
        radius = half.amax(-1).clamp_max(_MAX_RADIUS).ceil()
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    return Projection(
        means2d=means2d.to(dtype), conics=conics.to(dtype), depths=z.to(dtype), box=box, visible=visible, radii=radii
    )
