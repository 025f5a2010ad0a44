"""Parametric hand (MANO) and head (FLAME) templates: data model, official-file
loaders, linear blend skinning layers and procedural stand-ins.

Importing this package never touches the pipeline; see DESIGN.md ("Templates").
"""

from avatar.templates.layers import FLAMELayer, LayerOutput, MANOLayer
from avatar.templates.lbs import batch_rigid_transform, batch_rodrigues, lbs
from avatar.templates.loaders import OfficialModelError, load_landmark_embedding, load_official_model
from avatar.templates.model import TemplateModel
from avatar.templates.procedural import procedural_hand, procedural_head

__all__ = [
    "FLAMELayer",
    "LayerOutput",
    "MANOLayer",
    "OfficialModelError",
    "TemplateModel",
    "batch_rigid_transform",
    "batch_rodrigues",
    "lbs",
    "load_landmark_embedding",
    "load_official_model",
    "procedural_hand",
    "procedural_head",
]
