"""Contact deformation of the face by the hand: an XPBD solver (importable without the pipeline).

``problem`` (the solver's settings and one frame's XPBD system), ``solver`` (per-frame XPBD solve, sequences
with warm start), ``direct`` (the same fixed point by sparse solves), ``constraints`` (stretch, bending,
attachment, collision projections), ``collision`` (closest points and inside test on the hand), ``sequence``
(a sequence with per-frame report rows), ``topology`` (edges, bending stencils, colouring), ``stiffness``
(per-vertex stiffness from tissue thickness), ``convention`` (world vs DECAF canonical offsets),
``evaluation`` (errors against a reference deformation).
"""

from avatar.pbd.convention import world_to_decaf_offsets
from avatar.pbd.evaluation import VertexErrors, moving_vertex_errors
from avatar.pbd.problem import FaceTopology, PBDConfig
from avatar.pbd.sequence import SequenceDeformation, simulate_sequence
from avatar.pbd.solver import FrameResult, detect_contacts, single_threaded, solve_frame, solve_sequence
from avatar.pbd.stiffness import StiffnessFileError, face_relative_stiffness

__all__ = [
    "FaceTopology",
    "FrameResult",
    "PBDConfig",
    "SequenceDeformation",
    "StiffnessFileError",
    "VertexErrors",
    "detect_contacts",
    "face_relative_stiffness",
    "moving_vertex_errors",
    "simulate_sequence",
    "single_threaded",
    "solve_frame",
    "solve_sequence",
    "world_to_decaf_offsets",
]
