"""Gaussians embedded in a triangle mesh by barycentric coordinates and a normal displacement
(SplattingAvatar: Shao et al., CVPR 2024, "Realistic Real-Time Human Avatars with Mesh-Embedded
Gaussian Splatting").

Each Gaussian stores its triangle ``t``, barycentrics ``(u, v)`` (``w = 1 - u - v``, weights of the
triangle's vertices ``v0, v1, v2`` in that order), a displacement ``d``, a local rotation ``q``,
log-scales ``s``, an opacity logit and a degree-0 SH colour. On a posed mesh (vertices ``x``, vertex
normals ``n``, both of the frame):

- position: ``mu = u x0 + v x1 + w x2 + d * normalize(u n0 + v n1 + w n2)`` (a Phong-surface point
  lifted along the interpolated normal; ``model/splatting_avatar_model.py``, ``get_xyz`` with
  ``xyz_as_uvd``, of ``initialneil/SplattingAvatar``);
- scale: ``exp(s) * sqrt(area_posed(t) / area_canonical(t))``, so a mesh scaled by 2 doubles every
  Gaussian. The public code (``get_scaling``) computes ``exp(s * r)`` with the damped area ratio
  ``r = (a + 1e-4) / (a_cano + 1e-4)`` (``utils/map.py``, ``calc_face_area_change``), which, with
  areas in square metres, is close to 1 for FLAME-sized triangles and does not scale Gaussians with
  the mesh; here the ratio is damped by 1e-8 of the mean canonical area only, and follows the length
  scale (square root of the area ratio);
- rotation: ``R q`` where ``R`` takes the canonical mesh to the posed one at the Gaussian. The public
  code blends per-vertex quaternions (area-weighted averages over the adjacent faces of the rotation
  from each face's canonical tangent frame to its posed one, ``utils/map.py``, ``PerVertQuaternion``)
  with the barycentrics. Here: per face ``R_f = P_f C_f^T`` from the triangle frames of
  :mod:`avatar.geometry.frames` (first edge, normal) on the posed and canonical mesh; per vertex the
  canonical-area-weighted mean matrix of its faces' ``R_f`` (matrices, not quaternions, so no sign
  alignment is needed); at the Gaussian the barycentric blend ``M`` of its vertices' matrices,
  orthonormalised (Gram-Schmidt: first column, then second), then turned by the smallest rotation
  that takes ``M n_c`` (the rotated interpolated canonical normal) onto the interpolated posed normal
  ``n_p``. The Gaussian's frame is thus the interpolated vertex normal (the same one its displacement
  follows) plus a tangent from the blended vertex rotations; it depends only on vertex quantities,
  so it is continuous when a Gaussian walks to a neighbouring triangle, it is the identity on the
  canonical mesh (``q`` is the canonical world rotation) and exactly ``R0`` for a mesh moved
  rigidly by ``R0``.
- colour: ``rgb = max(0.5 + C0 * sh_dc, 0)`` and opacity ``sigmoid(logit)``, as
  :class:`avatar.representations.bound.gaussians.BoundGaussians`.

``u, v, d, q, s``, opacity and colour are optimised; ``u, v`` are true parameters with gradients
(in the public code the rendered position depends only on the buffer ``sample_bary``, so the ``uv``
part of ``_xyz`` never receives a gradient, ``walking_on_triangles`` walks by a zero shift, and only
split children move to other triangles). After a step, :meth:`walk` moves every
Gaussian that left its triangle onto its neighbour (:mod:`avatar.representations.embedded.walking`). Parts (face,
hand) are separate vertex sets, so a Gaussian never walks onto another part.

Initialisation (:meth:`EmbeddedGaussians.on_triangles`): ``per_triangle`` Gaussians per face (the
first at the centroid, the others uniform over it, as the static baseline), ``d = 0``, identity
rotation, isotropic scale ``sqrt(2 A / (pi K))`` for a face of area ``A`` holding ``K`` Gaussians
(the expected RMS distance to the 3 nearest neighbours at that density; the public code uses the
measured one, ``distCUDA2``), opacity ``init_opacity`` (public: 0.1), grey colour.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from avatar.geometry.frames import quaternion_multiply, rotation_to_quaternion, triangle_frames
from avatar.representations.bound.gaussians import SH_C0, check_initial_population, inverse_sigmoid
from avatar.representations.embedded.walking import WalkTable, build_walk_table, full_barycentric, walk

PARAM_NAMES = ("barycentric", "displacement", "log_scales", "quats", "opacity_logits", "sh_dc")
STATE_NAMES = ("triangle", "part", *PARAM_NAMES)
_AREA_DAMPING = 1e-8  # of the mean canonical face area
_MIN_INIT_AREA = 1e-4  # of the mean canonical face area, floor of the area behind the initial scales


def face_areas(vertices: Tensor, faces: Tensor) -> Tensor:
    """(F,) triangle areas of ``vertices`` (V, 3); finite gradients for degenerate faces."""
    tri = vertices[faces]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return 0.5 * torch.sqrt(cross.square().sum(-1) + 1e-30)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """(V, 3) area-weighted unit vertex normals (zero for vertices in no face)."""
    tri = vertices[faces]
    face_normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length 2 A
    total = torch.zeros_like(vertices)
    for corner in range(3):
        total = total.index_add(0, faces[:, corner], face_normal)
    return F.normalize(total, dim=-1, eps=1e-30)


def barycentric_blend(per_vertex: Tensor, corners: Tensor, bary: Tensor) -> Tensor:
    """Barycentric blend ``sum_c bary[:, c] per_vertex[corners[:, c]]``: (N, ...) from (V, ...), (N, 3), (N, 3)."""
    picked = per_vertex[corners]  # (N, 3, ...)
    weights = bary.reshape(*bary.shape, *([1] * (picked.dim() - 2)))
    return (weights * picked).sum(1)


def _smallest_rotation(a: Tensor, b: Tensor) -> Tensor:
    """(N, 3, 3) rotations taking unit vectors ``a`` (N, 3) onto ``b`` (N, 3) about ``a x b``
    (identity where either is zero; ``a = -b`` is clamped away)."""
    axis = torch.linalg.cross(a, b)
    cos = (a * b).sum(-1).clamp_min(-1.0 + 1e-6)
    zero = torch.zeros_like(cos)
    skew = torch.stack(
        [
            torch.stack([zero, -axis[:, 2], axis[:, 1]], -1),
            torch.stack([axis[:, 2], zero, -axis[:, 0]], -1),
            torch.stack([-axis[:, 1], axis[:, 0], zero], -1),
        ],
        dim=-2,
    )
    eye = torch.eye(3, dtype=a.dtype, device=a.device).expand_as(skew)
    return eye + skew + (skew @ skew) / (1.0 + cos)[:, None, None]


def _gram_schmidt(m: Tensor) -> Tensor:
    """(N, 3, 3) rotations from near-rotation matrices: first column, then the second made orthogonal."""
    x = F.normalize(m[..., 0], dim=-1, eps=1e-30)
    y = m[..., 1] - (x * m[..., 1]).sum(-1, keepdim=True) * x
    y = F.normalize(y, dim=-1, eps=1e-30)
    return torch.stack([x, y, torch.linalg.cross(x, y)], dim=-1)


class CanonicalMesh(nn.Module):
    """The canonical mesh the Gaussians are embedded in, and what :class:`EmbeddedGaussians` derives
    from it once (non-persistent buffers: rebuilt from ``vertices`` and ``faces``, never checkpointed).

    Attributes:
        vertices: (V, 3), faces: (F, 3) int64.
        areas: (F,) canonical face areas; ``area_damping`` the damping of the area ratio.
        normals: (V, 3) canonical unit vertex normals.
        frames: (F, 3, 3) canonical triangle frames (:func:`avatar.geometry.frames.triangle_frames`).
        face_weights: (F,) area weights of faces in the per-vertex rotations; ``vertex_weights`` (V,)
            their sum per vertex.
        walk_*: the :class:`avatar.representations.embedded.walking.WalkTable` fields.
    """

    vertices: Tensor
    faces: Tensor
    areas: Tensor
    area_damping: Tensor
    normals: Tensor
    frames: Tensor
    face_weights: Tensor
    vertex_weights: Tensor

    def __init__(self, vertices: Tensor, faces: Tensor) -> None:
        super().__init__()
        faces = faces.long()
        vertices = vertices.detach()
        areas = face_areas(vertices, faces)
        weights = torch.zeros(vertices.shape[0], dtype=vertices.dtype, device=vertices.device)
        for corner in range(3):
            weights = weights.index_add(0, faces[:, corner], areas)
        derived = {
            "vertices": vertices.clone(),
            "faces": faces.clone(),
            "areas": areas,
            "area_damping": _AREA_DAMPING * areas.mean() if len(areas) else areas.new_tensor(0.0),
            "normals": vertex_normals(vertices, faces),
            "frames": triangle_frames(vertices, faces).rotation,
            "face_weights": areas,
            "vertex_weights": weights,
        }
        for name, value in derived.items():
            self.register_buffer(name, value, persistent=False)
        for name, value in build_walk_table(vertices, faces).tensors().items():
            self.register_buffer(f"walk_{name}", value.to(vertices.device), persistent=False)

    @property
    def walk_table(self) -> WalkTable:
        return WalkTable(
            **{name[len("walk_") :]: buf for name, buf in self.named_buffers() if name.startswith("walk_")}
        )

    def area_scale(self, vertices: Tensor) -> Tensor:
        """(F,) ``sqrt(area_posed / area_canonical)`` (damped) of the posed ``vertices`` (V, 3)."""
        posed = face_areas(vertices, self.faces)
        return torch.sqrt((posed + self.area_damping) / (self.areas + self.area_damping))

    def vertex_rotations(self, vertices: Tensor) -> Tensor:
        """(V, 3, 3) area-weighted mean over each vertex's faces of the rotation from the canonical
        triangle frame to the posed one (not yet orthonormal)."""
        per_face = triangle_frames(vertices, self.faces).rotation @ self.frames.transpose(-1, -2)
        weighted = per_face * self.face_weights[:, None, None]
        total = vertices.new_zeros(vertices.shape[0], 3, 3)
        for corner in range(3):
            total = total.index_add(0, self.faces[:, corner], weighted)
        return total / self.vertex_weights.clamp_min(1e-30)[:, None, None]


class EmbeddedGaussians(nn.Module):
    """N Gaussians embedded in the triangles of a canonical mesh (all parts concatenated).

    Attributes:
        barycentric: (N, 2) parameter ``(u, v)``; ``w = 1 - u - v``.
        displacement: (N,) parameter, along the interpolated unit normal, world units.
        log_scales: (N, 3) parameter, log of the canonical world scale.
        quats: (N, 4) parameter, (w, x, y, z) rotation in the canonical world frame.
        opacity_logits: (N,) parameter.
        sh_dc: (N, 3) parameter, colour as degree-0 SH (``rgb = 0.5 + C0 * sh_dc``).
        triangle: (N,) int64 buffer, the face each Gaussian is embedded in.
        part: (N,) int64 buffer, the mesh (part) of that face.
        mesh: the :class:`CanonicalMesh`.
    """

    triangle: Tensor
    part: Tensor
    barycentric: nn.Parameter
    displacement: nn.Parameter
    log_scales: nn.Parameter
    quats: nn.Parameter
    opacity_logits: nn.Parameter
    sh_dc: nn.Parameter

    def __init__(
        self,
        mesh: CanonicalMesh,
        triangle: Tensor,
        part: Tensor,
        barycentric: Tensor,
        displacement: Tensor,
        log_scales: Tensor,
        quats: Tensor,
        opacity_logits: Tensor,
        sh_dc: Tensor,
    ) -> None:
        super().__init__()
        self.mesh = mesh
        self.register_buffer("triangle", triangle.long().clone())
        self.register_buffer("part", part.long().clone())
        values = (barycentric, displacement, log_scales, quats, opacity_logits, sh_dc)
        for name, value in zip(PARAM_NAMES, values, strict=True):
            setattr(self, name, nn.Parameter(value.detach().clone()))

    @classmethod
    def on_triangles(
        cls,
        canonical_vertices: Tensor,
        faces: Tensor,
        face_part: Tensor,
        per_triangle: int,
        init_opacity: float = 0.1,
        seed: int = 0,
        init_rgb: float = 0.5,
        populate: Tensor | None = None,
    ) -> EmbeddedGaussians:
        """``per_triangle`` Gaussians on every face of the canonical mesh.

        Args:
            canonical_vertices: (V, 3) canonical vertices of all parts (their dtype is the model's).
            faces: (F, 3) int64. face_part: (F,) int64 part of each face.
            per_triangle: Gaussians per face; the first at the centroid, the others uniform over it.
            init_opacity: initial opacity, strictly between 0 and 1.
            seed: seed of the barycentric sampling.
            populate: (F,) bool, the faces that get Gaussians; None: all. (Walking can later carry a
                Gaussian onto an empty face of the same part.)
        """
        check_initial_population(per_triangle, init_opacity)
        mesh = CanonicalMesh(canonical_vertices, faces)
        dtype, num_faces = canonical_vertices.dtype, faces.shape[0]
        gen = torch.Generator().manual_seed(seed)
        exponential = -torch.log(torch.rand(num_faces, per_triangle, 3, generator=gen, dtype=dtype).clamp_min(1e-12))
        bary = exponential / exponential.sum(-1, keepdim=True)  # Dirichlet(1, 1, 1): uniform on the face
        bary[:, 0] = 1.0 / 3.0
        chosen = torch.arange(num_faces) if populate is None else torch.nonzero(populate.cpu()).flatten()
        triangle = chosen.repeat_interleave(per_triangle)
        n = len(chosen) * per_triangle
        area = mesh.areas.cpu().clamp_min(_MIN_INIT_AREA * float(mesh.areas.mean()))
        log_scale = 0.5 * torch.log(2.0 * area / (math.pi * per_triangle))
        quats = torch.zeros(n, 4, dtype=dtype)
        quats[:, 0] = 1.0
        device = canonical_vertices.device
        model = cls(
            mesh,
            triangle,
            face_part.long().cpu()[triangle],
            bary[chosen].reshape(n, 3)[:, :2],
            torch.zeros(n, dtype=dtype),
            log_scale[triangle, None].expand(n, 3).to(dtype),
            quats,
            inverse_sigmoid(torch.full((n,), init_opacity, dtype=dtype)),
            torch.full((n, 3), (init_rgb - 0.5) / SH_C0, dtype=dtype),
        )
        return model.to(device)

    @classmethod
    def from_state_tensors(
        cls, state: dict[str, Tensor], canonical_vertices: Tensor, faces: Tensor
    ) -> EmbeddedGaussians:
        """The model of :meth:`state_tensors` on the canonical mesh ``canonical_vertices`` (V, 3), ``faces`` (F, 3)."""
        missing = [name for name in STATE_NAMES if name not in state]
        if missing:
            raise ValueError(f"embedded Gaussians state lacks {', '.join(missing)}")
        triangle = state["triangle"].long()
        if len(triangle) and (int(triangle.min()) < 0 or int(triangle.max()) >= faces.shape[0]):
            raise ValueError(f"embedded Gaussians state: triangle indices outside [0, {faces.shape[0]})")
        dtype = canonical_vertices.dtype
        params = [state[name].to(dtype) for name in PARAM_NAMES]
        return cls(CanonicalMesh(canonical_vertices, faces), triangle, state["part"], *params)

    def state_tensors(self) -> dict[str, Tensor]:
        """Detached copies: ``triangle`` (N,) int64, ``part`` (N,) int64, ``barycentric`` (N, 2),
        ``displacement`` (N,), ``log_scales`` (N, 3), ``quats`` (N, 4), ``opacity_logits`` (N,), ``sh_dc`` (N, 3)."""
        return {name: getattr(self, name).detach().clone() for name in STATE_NAMES}

    def resize_like(self, state: dict[str, Tensor]) -> None:
        """Give parameters and buffers the shapes they have in ``state`` (a ``state_dict`` written after
        density control changed N), before ``load_state_dict``."""
        for name in STATE_NAMES:
            empty = torch.empty_like(state[name])
            setattr(self, name, nn.Parameter(empty) if name in PARAM_NAMES else empty)

    @property
    def num_gaussians(self) -> int:
        return self.triangle.shape[0]

    def opacities(self) -> Tensor:
        """(N,) opacity in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def colors(self) -> Tensor:
        """(N, 3) linear RGB, clamped at 0 like the 3DGS SH evaluation."""
        return torch.clamp_min(0.5 + SH_C0 * self.sh_dc, 0.0)

    @torch.no_grad()
    def set_colors(self, rgb: Tensor) -> None:
        """Set the colours from linear RGB (N, 3) in [0, 1]."""
        self.sh_dc.copy_((rgb - 0.5) / SH_C0)

    def corners(self) -> Tensor:
        """(N, 3) int64 vertex indices of each Gaussian's triangle."""
        return self.mesh.faces[self.triangle]

    def world(self, vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """World means (N, 3), linear scales (N, 3) and quaternions (N, 4, w x y z) on the posed mesh.

        Args:
            vertices: (V, 3) posed vertices, same topology as the canonical mesh.
            faces: (F, 3) its faces (those of the canonical mesh).
        """
        corners = faces[self.triangle]
        bary = full_barycentric(self.barycentric)
        normals = barycentric_blend(vertex_normals(vertices, faces), corners, bary)
        posed_normal = F.normalize(normals, dim=-1, eps=1e-30)
        means = barycentric_blend(vertices, corners, bary) + self.displacement[:, None] * posed_normal
        scales = torch.exp(self.log_scales) * self.mesh.area_scale(vertices)[self.triangle, None]
        rotation = self._rotation(vertices, corners, bary, posed_normal)
        return means, scales, quaternion_multiply(rotation_to_quaternion(rotation), self.quats)

    def forward(self, vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Same as :meth:`world`."""
        return self.world(vertices, faces)

    def _rotation(self, vertices: Tensor, corners: Tensor, bary: Tensor, posed_normal: Tensor) -> Tensor:
        """(N, 3, 3) canonical-to-posed rotation at each Gaussian (module docstring)."""
        blended = _gram_schmidt(barycentric_blend(self.mesh.vertex_rotations(vertices), corners, bary))
        canonical_normal = F.normalize(barycentric_blend(self.mesh.normals, corners, bary), dim=-1, eps=1e-30)
        turned = (blended @ canonical_normal[..., None])[..., 0]
        return _smallest_rotation(turned, posed_normal) @ blended

    @torch.no_grad()
    def walk(self, max_hops: int = 64) -> Tensor:
        """Move every Gaussian that left its triangle onto the triangle it walked to (all its
        parameters stay in its row); returns (N,) bool, which Gaussians changed triangle."""
        triangle, uv = walk(self.mesh.walk_table, self.triangle, self.barycentric, max_hops)
        changed = triangle != self.triangle
        self.triangle.copy_(triangle)
        self.barycentric.copy_(uv)
        return changed
