"""Rendering the Gaussians of one frame from a view of a sequence, as training, evaluation and tracking do."""

from __future__ import annotations

from avatar.geometry.views import ViewSet
from avatar.render.gaussians import WorldGaussians, render_gaussians


def rasterize(g: WorldGaussians, views: ViewSet, camera: int, backend: str = "auto"):  # RenderOutput
    """Render the Gaussians of one frame from view ``camera`` of ``views``."""
    return render_gaussians(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.colors,
        views.K[camera],
        views.world_to_cam[camera],
        views.size,
        views.size,
        views.background,
        backend=backend,
    )
