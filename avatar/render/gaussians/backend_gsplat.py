"""Adapter to gsplat's CUDA rasterizer (``gsplat.rasterization``, gsplat 1.5.3, the ``cuda`` extra).

Conventions, and where they differ from the project's ``torch`` and ``cpu`` backends:

* pixel centres: gsplat puts pixel ``(i, j)``'s centre at ``(j + 0.5, i + 0.5)``, this project at ``(j, i)``
  (OpenCV): the adapter shifts the principal point by +0.5 before calling gsplat and its ``means2d`` by -0.5;
* radii: gsplat returns per-axis radii (N, 2), the adapter their maximum, as the project's (N,);
* 2D means of culled Gaussians (radius 0): gsplat's CUDA projection never writes them (uninitialised memory,
  seen as 6.6e9 px on an H200); the adapter returns 0 there (the project's backends, the projection of a
  safe point): they are defined only where the radius is positive, in every backend;
* alpha: gsplat clamps at 0.999 (the project's backends at 0.99, as 3DGS), so the two differ where
  ``opacity * G > 0.99``; it stops a pixel once ``T <= 1e-4`` (the project's: ``< 1e-4``);
* culling: the adapter culls before gsplat what the project's backends cull (camera depth outside
  ``[near, far]`` computed in float64, any non-finite parameter): such a Gaussian is parked beyond the far
  plane with opacity 0, so it draws nothing and gets a zero gradient (gsplat's PyTorch reference returns NaN
  gradients for a mean on the camera plane, and float32 NaNs would reach the image). gsplat itself gets a
  depth range :data:`DEPTH_SLACK` wider, so that its float32 depth of a Gaussian within rounding of the near
  plane does not cull it a second time;
* quaternions are normalised here, robustly (a zero or denormal quaternion is the identity, as in the
  project's backends; gsplat's own normalisation of ``[1e-30, 0, 0, 0]`` underflows);
* no Gaussians at all: gsplat 1.5.3's CUDA launcher divides by their number (SIGFPE, the whole process
  dies); the adapter returns the background image itself;
* huge scales: gsplat works in float32 throughout, and a 2D covariance past ~1e19 px^2 overflows its
  determinant; the adapter caps a Gaussian's world scale at :data:`MAX_STD_PX` pixels of standard deviation
  at its depth, where it is already one flat colour over any image (its scale gradient is 0 beyond).

``tests/render/gaussians/test_gs_gsplat_adapter.py`` runs this adapter on the CPU through gsplat's PyTorch
reference and compares it with the project's backends; ``test_gs_gsplat.py`` runs the CUDA kernels
(``make test-gpu``).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from .output import RenderOutput


@functools.cache
def gsplat_available() -> bool:
    """True when ``import gsplat`` works and a CUDA device is present."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # an install without its CUDA extension fails in many ways
        return False
    return True


#: projected standard deviation (pixels) at which the adapter caps a Gaussian's scale (see the module docstring)
MAX_STD_PX = 1e6
#: relative widening of ``[near, far]`` passed to gsplat (the adapter has culled by depth already)
DEPTH_SLACK = 1e-3


def _identity(like: Tensor) -> Tensor:
    """(4,) the identity quaternion (w, x, y, z) in ``like``'s dtype and device, filled there: no copy from the host,
    which on a GPU would wait for the device."""
    identity = like.new_zeros(4)
    identity[0] = 1.0
    return identity


def unit_quaternions(quats: Tensor) -> Tensor:
    """(N, 4) -> (N, 4) unit quaternions; a zero row becomes the identity. Divides by the largest
    component first, so that tiny quaternions (1e-30) do not underflow."""
    largest = quats.abs().amax(-1, keepdim=True)
    zero = ~(largest > 0)
    scaled = quats / torch.where(zero, torch.ones_like(largest), largest)
    scaled = torch.where(zero, _identity(scaled), scaled)
    return scaled / scaled.norm(dim=-1, keepdim=True)


def gsplat_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    near: float,
    far: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The Gaussians as gsplat should see them: culled ones parked beyond ``far`` with opacity 0 (zero
    gradient), unit quaternions, scales capped at :data:`MAX_STD_PX`. Shapes as the inputs: (N, 3),
    (N, 4), (N, 3), (N,)."""
    with torch.no_grad():
        view = world_to_cam.detach().to(torch.float64)
        depth = means.detach().to(torch.float64) @ view[2, :3] + view[2, 3]  # float64, as the project's backends
        keep = (depth >= near) & (depth <= far) & torch.isfinite(depth)
        for tensor in (quats, scales):
            keep &= torch.isfinite(tensor.detach()).all(-1)
        keep &= torch.isfinite(opacities.detach())
        # the camera-space point (0, 0, 2 far) in the world, R^T ((0, 0, 2 far) - t), from the device's own values
        parked = (2.0 * far * view[2, :3] - view[:3, :3].T @ view[:3, 3]).to(means)
        focal = K.detach().diagonal()[:2].max().to(torch.float64)  # a tensor: not read on the host
        max_scale = ((MAX_STD_PX / focal) * depth.clamp(near, far)).to(scales)
    keep_col = keep[:, None]
    means = torch.where(keep_col, means, parked)
    quats = torch.where(
        keep_col, unit_quaternions(torch.where(keep_col, quats, torch.ones_like(quats))), _identity(quats)
    )
    scales = torch.where(keep_col, torch.minimum(scales, max_scale[:, None]), torch.ones_like(scales))
    opacities = torch.where(keep, opacities, torch.zeros_like(opacities))
    return means, quats, scales, opacities


def _background_only(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    width: int,
    height: int,
    background: Tensor,
) -> RenderOutput:
    """The image of no Gaussians: the background everywhere, alpha and depth 0; (0, 2) means2d. The zero sums
    keep the (empty) inputs in the graph, so that ``backward()`` works as with Gaussians."""
    zero = sum(t.sum() for t in (means, quats, scales, opacities, colors)) * 0
    holder = means.new_zeros(0, 2).requires_grad_(means.requires_grad)
    return RenderOutput(
        rgb=background.expand(height, width, 3) + zero,
        alpha=means.new_zeros(height, width) + zero,
        depth=means.new_zeros(height, width) + zero,
        means2d=holder,
        radii=torch.zeros(0, dtype=torch.int32, device=means.device),
        grad_holder=holder,
    )


def render_gsplat(
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
) -> RenderOutput:
    """Render N Gaussians with ``gsplat.rasterization`` (arguments and outputs as ``render_gaussians``).

    float32 CUDA inputs render where they are. CPU inputs (a pipeline that trains on the CPU with
    ``backend=gsplat``) are copied to the GPU when one is present and the outputs copied back, the gradients
    flowing through both copies; without a GPU they stay where they are (gsplat's PyTorch reference, tests).
    """
    import gsplat

    if means.shape[0] == 0:  # gsplat 1.5.3's CUDA launcher divides by N (SIGFPE): nothing to draw anyway
        return _background_only(means, quats, scales, opacities, colors, width, height, background)
    device = means.device
    if device.type != "cuda" and torch.cuda.is_available():
        out = render_gsplat(
            means.cuda(),
            quats.cuda(),
            scales.cuda(),
            opacities.cuda(),
            colors.cuda(),
            K.cuda(),
            world_to_cam.cuda(),
            width,
            height,
            background.cuda(),
            near=near,
            far=far,
        )
        return RenderOutput(
            rgb=out.rgb.to(device),
            alpha=out.alpha.to(device),
            depth=out.depth.to(device),
            means2d=out.means2d.to(device),
            radii=out.radii.to(device),
            grad_holder=out.grad_holder,
        )

    means, quats, scales, opacities = gsplat_inputs(means, quats, scales, opacities, K, world_to_cam, near, far)
    k_gsplat = K.detach().clone().to(means)
    k_gsplat[:2, 2] += 0.5
    colors_depth, alphas, meta = gsplat.rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=world_to_cam.detach().to(means)[None],
        Ks=k_gsplat[None],
        width=width,
        height=height,
        near_plane=near * (1 - DEPTH_SLACK),
        far_plane=far * (1 + DEPTH_SLACK),
        backgrounds=background.to(means)[None],
        render_mode="RGB+D",
        packed=False,
        rasterize_mode="classic",
    )
    holder = meta["means2d"]  # (1, N, 2), gsplat's pixel frame
    if holder.requires_grad:
        holder.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5: per-axis radii (N, 2)
        radii = radii.amax(-1)
    radii = radii.to(torch.int32)
    means2d = torch.where(radii[:, None] > 0, holder[0] - 0.5, torch.zeros_like(holder[0]))  # see the docstring
    return RenderOutput(
        rgb=colors_depth[0, ..., :3],
        alpha=alphas[0, ..., 0],
        depth=colors_depth[0, ..., 3],
        means2d=means2d,
        radii=radii,
        grad_holder=holder,
    )
