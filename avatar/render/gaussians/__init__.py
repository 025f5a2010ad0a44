"""Differentiable 3D Gaussian rasterizer: one interface (``render_gaussians``), several backends.

``torch`` (pure PyTorch, any device, the reference), ``cpu`` (compiled C++/OpenMP, CPU) and
``gsplat`` (CUDA). Modules: ``projection`` (EWA projection), ``tiling`` (tile binning and depth
sort), ``compositing`` (alpha compositing with a hand-written backward), ``backend_torch``,
``backend_cpu`` (with ``extension``, which builds ``csrc/``), ``backend_gsplat``, ``render``
(backend choice), ``output`` (``RenderOutput``), ``world`` (``WorldGaussians``, what a posed model hands
the rasterizer).
"""

from .output import RenderOutput
from .render import available_backends, render_gaussians, resolve_backend
from .world import WorldGaussians

__all__ = ["RenderOutput", "WorldGaussians", "available_backends", "render_gaussians", "resolve_backend"]
