"""SplattingAvatar (Shao et al., CVPR 2024): Gaussians embedded in mesh triangles by barycentric
coordinates and a normal displacement, walking across triangles as they are optimised.

Modules: ``embedding`` (the model), ``walking`` (edge adjacency, triangle walking), ``density``
(3DGS density control for embedded Gaussians); the training loop is :mod:`avatar.representations.embedded.training`.
"""

from avatar.representations.embedded.embedding import EmbeddedGaussians

__all__ = ["EmbeddedGaussians"]
