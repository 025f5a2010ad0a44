"""``render_gaussians``: one interface over the rasterizer backends, picked at run time."""

from __future__ import annotations

from torch import Tensor

from .backend_cpu import DTYPES as CPU_DTYPES
from .backend_cpu import render_cpu
from .backend_gsplat import gsplat_available, render_gsplat
from .backend_torch import render_torch
from .extension import cpu_extension_available, unavailable_reason
from .output import RenderOutput

BACKENDS = ("torch", "cpu", "gsplat")
_RENDERERS = {"torch": render_torch, "cpu": render_cpu, "gsplat": render_gsplat}


def available_backends() -> list[str]:
    """Backends usable in this process: always ``torch``; ``cpu`` once the compiled extension is
    built (building it on first call); ``gsplat`` with CUDA and gsplat installed."""
    usable = {"torch": True, "cpu": cpu_extension_available(), "gsplat": gsplat_available()}
    return [name for name in BACKENDS if usable[name]]


def resolve_backend(backend: str, means: Tensor) -> str:
    """The concrete backend for a request. ``auto`` picks gsplat for float32 CUDA inputs and the
    compiled ``cpu`` backend for float32/float64 CPU inputs when they are available, else torch."""
    if backend == "auto":
        use_gsplat = means.is_cuda and means.dtype.is_floating_point and means.element_size() == 4
        if use_gsplat and gsplat_available():
            return "gsplat"
        use_cpu = means.device.type == "cpu" and means.dtype in CPU_DTYPES
        return "cpu" if use_cpu and cpu_extension_available() else "torch"
    if backend not in BACKENDS:
        raise ValueError(f"unknown Gaussian rasterizer backend {backend!r}; choose one of auto, {', '.join(BACKENDS)}")
    if backend == "gsplat" and not gsplat_available():
        raise RuntimeError(
            "backend 'gsplat' needs CUDA and the gsplat package (pip install gsplat); use backend='torch' or 'auto'"
        )
    if backend == "cpu" and not cpu_extension_available():
        raise RuntimeError(
            f"backend 'cpu' (the compiled CPU rasterizer) is unavailable: {unavailable_reason()}; "
            "use backend='torch' or 'auto'"
        )
    return backend


def _check_shapes(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    background: Tensor,
) -> None:
    n = means.shape[0]
    expected = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
        "colors": (colors, (n, 3)),
        "K": (K, (3, 3)),
        "world_to_cam": (world_to_cam, (4, 4)),
        "background": (background, (3,)),
    }
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"render_gaussians: {name} has shape {tuple(tensor.shape)}, expected {shape}")


def render_gaussians(
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
    backend: str = "auto",
    near: float = 0.01,
    far: float = 100.0,
) -> RenderOutput:
    """Render N 3D Gaussians into one view.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations, not necessarily normalised.
        scales: (N, 3) linear (not log) standard deviations.
        opacities: (N,) in [0, 1].
        colors: (N, 3) RGB.
        K: (3, 3) OpenCV intrinsics; pixel ``(row i, col j)`` has its centre at ``(x, y) = (j, i)``.
        world_to_cam: (4, 4) rigid transform, OpenCV camera axes (x right, y down, z forward).
        width, height: image size in pixels.
        background: (3,) colour behind the Gaussians.
        backend: ``auto`` (gsplat on float32 CUDA inputs, the compiled ``cpu`` backend on
            float32/float64 CPU inputs, when available; else torch), ``torch``, ``cpu`` or ``gsplat``.
        near, far: Gaussians with camera z outside ``[near, far]`` are culled.

    Differentiable w.r.t. means, quats, scales, opacities, colors and background (not the
    camera). ``RenderOutput.grad2d()`` gives ``dL/dmeans2d`` after ``backward()``.
    """
    _check_shapes(means, quats, scales, opacities, colors, K, world_to_cam, background)
    render = _RENDERERS[resolve_backend(backend, means)]
    return render(
        means, quats, scales, opacities, colors, K, world_to_cam, width, height, background, near=near, far=far
    )
