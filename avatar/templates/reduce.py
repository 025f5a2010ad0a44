"""A template cut down to what its keypoints need, for fast fitting.

Fitting evaluates keypoints hundreds of times; skinning every vertex for 21
hand keypoints (joints plus 5 fingertip vertices) or 68 face landmarks (on a
few hundred triangles) wastes most of the work. :func:`keypoint_template`
keeps only those vertices and adds one *joint vertex* per joint whose shaped
position is exactly the regressed joint (template ``J_regressor @ v_template``,
blend shapes ``J_regressor @ shapedirs``) and whose regressor row is the
identity. Skinning the reduced template therefore gives the same joints and
the same kept vertices as the full one, to rounding.
"""

from __future__ import annotations

import numpy as np

from avatar.templates.model import TemplateModel


def _kept_vertices(model: TemplateModel) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids to keep and the reduced faces (indices into the full mesh)."""
    if model.tip_vertex_ids is not None:
        tips = np.asarray(model.tip_vertex_ids)
        return tips, tips[None, :3]  # one placeholder triangle: a template needs a face
    if model.landmark_faces is not None:
        faces = np.asarray(model.faces)[model.landmark_faces]
        return np.unique(faces), faces
    raise ValueError(
        f"TemplateModel({model.name}) has neither tip_vertex_ids nor a landmark embedding: "
        "it has no keypoints to reduce to"
    )


def keypoint_template(model: TemplateModel) -> TemplateModel:
    """The template restricted to its keypoint vertices plus one joint vertex per joint.

    MANO (``tip_vertex_ids`` set): keeps the 5 fingertips, ``tip_vertex_ids`` becomes 0..4.
    FLAME (landmark embedding set): keeps the landmark triangles' vertices; the
    faces are the landmark triangles and ``landmark_faces`` becomes 0..L-1.
    Vertex-wise extras (``inner_distance``, ``part_labels``) are dropped.
    """
    kept, faces = _kept_vertices(model)
    remap = np.full(model.num_vertices, -1, np.int64)
    remap[kept] = np.arange(len(kept))
    J, K = model.num_joints, len(kept)
    joint_template = model.J_regressor @ model.v_template  # (J, 3)
    joint_shapedirs = np.einsum("jv,vcs->jcs", model.J_regressor, model.shapedirs)  # (J, 3, S)
    joint_weights = np.zeros((J, J))
    joint_weights[:, 0] = 1.0  # never used: joint vertices are only read before skinning
    is_mano = model.tip_vertex_ids is not None
    return TemplateModel(
        name=model.name,
        v_template=np.concatenate((model.v_template[kept], joint_template)),
        shapedirs=np.concatenate((model.shapedirs[kept], joint_shapedirs)),
        posedirs=np.concatenate((model.posedirs[kept], np.zeros((J, *model.posedirs.shape[1:])))),
        J_regressor=np.concatenate((np.zeros((J, K)), np.eye(J)), axis=1),
        weights=np.concatenate((model.weights[kept], joint_weights)),
        kintree_table=model.kintree_table,
        faces=remap[faces],
        hands_components=model.hands_components,
        hands_mean=model.hands_mean,
        num_shape=model.num_shape,
        landmark_faces=None if is_mano else np.arange(len(faces)),
        landmark_bary=None if is_mano else model.landmark_bary,
        tip_vertex_ids=np.arange(5) if is_mano else None,
    )
