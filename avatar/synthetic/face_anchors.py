"""Named contact anchors on the head template (the hand keys' targets).

Each anchor is one template vertex, found once on the rest template by casting
a ray from the head centre in a fixed head-frame direction (x: subject's left,
y: up, z: forward) and taking the outward-facing vertex closest to the ray.
The head centre is the centre of the face landmarks pushed back into the skull.
Anchors are on the subject's right side (-x), where the right hand works.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatar.synthetic.geometry import vertex_normals
from avatar.templates.layers import FLAMELayer

#: Ray directions (head frame) of the anchors.
DIRECTIONS = {
    "cheek": (-0.62, -0.25, 0.75),
    "jaw": (-0.65, -0.60, 0.45),
    "chin": (0.0, -0.62, 0.78),
    "mouth": (0.0, -0.35, 0.94),
    "temple": (-0.80, 0.45, 0.40),
}
#: The head centre lies this far behind the landmarks' centre (metres, -z).
CENTRE_DEPTH_M = 0.07


@dataclass(frozen=True)
class FaceAnchors:
    """Anchor name -> template vertex index."""

    vertices: dict[str, int]

    def vertex(self, name: str) -> int:
        """Vertex index of anchor ``name``."""
        if name not in self.vertices:
            raise KeyError(f"unknown face anchor {name!r}; known: {sorted(self.vertices)}")
        return self.vertices[name]

    @staticmethod
    def build(flame: FLAMELayer) -> FaceAnchors:
        """Anchors on the rest template of ``flame``."""
        rest = flame.v_template[None]
        centre = flame.landmarks(rest)[0].mean(dim=0).numpy() - np.array([0.0, 0.0, CENTRE_DEPTH_M])
        verts = rest[0].numpy()
        normals = vertex_normals(rest[0], flame.faces).numpy()
        rel = verts - centre
        rel /= np.linalg.norm(rel, axis=1, keepdims=True)
        found = {}
        for name, direction in DIRECTIONS.items():
            d = np.asarray(direction) / np.linalg.norm(direction)
            score = rel @ d - 2.0 * (normals @ d < 0.3)
            found[name] = int(np.argmax(score))
        return FaceAnchors(found)
