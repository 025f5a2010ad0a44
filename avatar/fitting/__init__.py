"""Multi-view FLAME/MANO fitting to 2D keypoints: robust triangulation, rigid
initialisation, batched sequence optimisation, detector-noise simulation and
accuracy metrics."""

from avatar.fitting.errors import landmark_error, mpjpe, per_vertex_error
from avatar.fitting.fit import FitConfig, FitResult, fit_sequence
from avatar.fitting.noise import corrupt_keypoints
from avatar.fitting.triangulation import Triangulation, projection_matrices, triangulate

__all__ = [
    "FitConfig",
    "FitResult",
    "Triangulation",
    "corrupt_keypoints",
    "fit_sequence",
    "landmark_error",
    "mpjpe",
    "per_vertex_error",
    "projection_matrices",
    "triangulate",
]
