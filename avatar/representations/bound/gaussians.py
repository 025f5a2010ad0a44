"""Static Gaussians bound to the triangles of one or more meshes (the GaussianAvatars model).

Each Gaussian stores its parameters in the local frame of its parent triangle
(see :mod:`avatar.geometry.frames`): ``local_means`` and ``log_scales`` in units
of the frame scale k, ``quats`` relative to the frame, plus an opacity logit and
a degree-0 SH colour. ``binding`` (N,) holds the parent triangle index into the
concatenation of all meshes' faces, and ``part`` (N,) which mesh it belongs to.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from avatar.geometry.frames import place_gaussians, triangle_frames

SH_C0 = 0.28209479177387814
PARAM_NAMES = ("local_means", "log_scales", "quats", "opacity_logits", "sh_dc")


def check_initial_population(per_triangle: int, init_opacity: float) -> None:
    """ValueError unless ``per_triangle`` >= 1 and ``init_opacity`` lies strictly between 0 and 1 (which also
    refuses NaN: 0 and 1 have infinite logits). Every representation's ``on_triangles`` calls it."""
    if per_triangle < 1:
        raise ValueError(f"per_triangle must be >= 1, got {per_triangle}")
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"init_opacity must lie strictly between 0 and 1, got {init_opacity}")


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1 - x))


class BoundGaussians(nn.Module):
    """N Gaussians bound to F triangles.

    Attributes:
        local_means: (N, 3) parameter, position in the parent frame (units of k).
        log_scales: (N, 3) parameter, log of the scale in units of k.
        quats: (N, 4) parameter, (w, x, y, z) rotation relative to the parent frame.
        opacity_logits: (N,) parameter.
        sh_dc: (N, 3) parameter, colour as degree-0 SH (``rgb = 0.5 + C0 * sh_dc``).
        binding: (N,) int64 buffer, parent triangle.
        part: (N,) int64 buffer, mesh index of the parent triangle.
    """

    binding: Tensor
    part: Tensor

    def __init__(
        self,
        local_means: Tensor,
        log_scales: Tensor,
        quats: Tensor,
        opacity_logits: Tensor,
        sh_dc: Tensor,
        binding: Tensor,
        part: Tensor,
    ) -> None:
        super().__init__()
        self.local_means = nn.Parameter(local_means)
        self.log_scales = nn.Parameter(log_scales)
        self.quats = nn.Parameter(quats)
        self.opacity_logits = nn.Parameter(opacity_logits)
        self.sh_dc = nn.Parameter(sh_dc)
        self.register_buffer("binding", binding.long())
        self.register_buffer("part", part.long())

    @classmethod
    def on_triangles(
        cls,
        vertices: Tensor,
        faces: Tensor,
        face_part: Tensor,
        per_triangle: int,
        init_opacity: float = 0.1,
        init_rgb: float = 0.5,
        seed: int = 0,
        populate: Tensor | None = None,
    ) -> BoundGaussians:
        """``per_triangle`` Gaussians spread over every triangle of the rest mesh (or of ``populate``).

        Args:
            vertices: (V, 3) rest-pose vertices of all meshes concatenated.
            faces: (F, 3) faces indexing ``vertices``.
            face_part: (F,) mesh index of each face.
            per_triangle: Gaussians per triangle (paper: 20); the first sits at the centroid, the
                others uniformly at random over the triangle; isotropic scales of 0.6 k / sqrt(per_triangle)
                so that together they cover it.
            populate: (F,) bool, the triangles that get Gaussians (e.g. only the face's when the scene has
                no hand); None: all. The others stay empty, and density control never fills them.
        """
        check_initial_population(per_triangle, init_opacity)
        gen = torch.Generator().manual_seed(seed)
        F = faces.shape[0]
        frames = triangle_frames(vertices, faces)
        uniform = torch.rand(F, per_triangle, 3, generator=gen, dtype=vertices.dtype)
        bary = -torch.log(uniform.clamp_min(1e-12))  # Dirichlet(1, 1, 1): uniform over the triangle
        bary = bary / bary.sum(-1, keepdim=True)
        bary[:, 0] = 1.0 / 3.0  # the first Gaussian of each triangle sits at the centroid
        points = torch.einsum("fkc,fcd->fkd", bary, vertices[faces])  # (F, K, 3)
        local = torch.einsum("fdj,fkd->fkj", frames.rotation, points - frames.origin[:, None])
        local = local / frames.scale[:, None, None]
        chosen = torch.arange(F) if populate is None else torch.nonzero(populate.cpu()).flatten()
        binding = chosen.repeat_interleave(per_triangle)
        n = len(chosen) * per_triangle
        log_scale = math.log(0.6 / math.sqrt(per_triangle))
        quats = torch.zeros(n, 4, dtype=vertices.dtype)
        quats[:, 0] = 1.0
        return cls(
            local_means=local[chosen].reshape(n, 3).clone(),
            log_scales=torch.full((n, 3), log_scale, dtype=vertices.dtype),
            quats=quats,
            opacity_logits=inverse_sigmoid(torch.full((n,), init_opacity, dtype=vertices.dtype)),
            sh_dc=torch.full((n, 3), (init_rgb - 0.5) / SH_C0, dtype=vertices.dtype),
            binding=binding,
            part=face_part[binding],
        )

    def resize_like(self, state: dict[str, Tensor]) -> None:
        """Give every parameter and buffer the shape it has in ``state`` (before ``load_state_dict``
        of a checkpoint written after density control changed N)."""
        for name in PARAM_NAMES:
            setattr(self, name, nn.Parameter(torch.empty_like(state[name])))
        self.binding = torch.empty_like(state["binding"])
        self.part = torch.empty_like(state["part"])

    @property
    def num_gaussians(self) -> int:
        return self.binding.shape[0]

    @torch.no_grad()
    def set_colors(self, rgb: Tensor) -> None:
        """Set the colours from linear RGB (N, 3) in [0, 1]."""
        self.sh_dc.copy_((rgb - 0.5) / SH_C0)

    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    def colors(self) -> Tensor:
        """(N, 3) linear RGB, clamped at 0 like the 3DGS SH evaluation."""
        return torch.clamp_min(0.5 + SH_C0 * self.sh_dc, 0.0)

    def world(self, vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """World means (N, 3), linear scales (N, 3) and quaternions (N, 4) on the posed mesh ``vertices`` (V, 3)."""
        return place_gaussians(
            triangle_frames(vertices, faces), self.binding, self.local_means, torch.exp(self.log_scales), self.quats
        )
