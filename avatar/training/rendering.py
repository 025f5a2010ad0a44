"""Rendering the Gaussians of one frame from a view of a sequence, as training, evaluation and tracking do."""

from __future__ import annotations

from torch import Tensor

from avatar.geometry.views import ViewSet
from avatar.render.gaussians import RenderOutput, WorldGaussians, render_gaussians


def render_view(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    views: ViewSet,
    camera: int,
    backend: str = "auto",
) -> RenderOutput:
    """Render N Gaussians (world means (N, 3), unit quaternions (N, 4), scales (N, 3), opacities (N,), colours
    (N, 3)) from view ``camera`` of ``views``, on its square crop and background."""
    return render_gaussians(
        means,
        quats,
        scales,
        opacities,
        colors,
        views.K[camera],
        views.world_to_cam[camera],
        views.size,
        views.size,
        views.background,
        backend=backend,
    )


def rasterize(g: WorldGaussians, views: ViewSet, camera: int, backend: str = "auto") -> RenderOutput:
    """Render the Gaussians of one frame from view ``camera`` of ``views``."""
    return render_view(g.means, g.quats, g.scales, g.opacities, g.colors, views, camera, backend)
