"""The dynamic InteractAvatar model: warm-up Gaussians plus the hand MLPs H and the interaction MLPs I.

Per frame (paper, Method):

- hand Gaussians: ``d_mu, d_s, d_q = H_geo(gamma(mu_cano), theta_hand)`` and
  ``d_c, d_o = H_app(gamma(mu_cano), P_i, F, theta_hand, r_hand, r_rel, t_rel)``;
- face Gaussians within ``d_max`` of the hand: ``d_mu, d_s, d_q, d_c, d_o =
  I(gamma(mu_cano), gamma(d_j), F, theta_hand, theta_face, psi, t_rel, r_rel)``, applied with the weight
  ``w_i = (cos(pi d_i / d_max) + 1) / 2`` (``d_i`` the distance of the Gaussian to the nearest hand vertex,
  0 beyond ``d_max``); I runs only on the Gaussians with ``w_i > 0``, so a frame without the hand near the
  face costs nothing;
- ``F``: PointNet++ over one Gaussian per deforming face triangle (``|d_j|`` above a threshold) and per hand
  triangle, drawn with probability proportional to ``o_i ||s_i||`` (the most probable one at evaluation),
  in the head frame.

How the deltas enter (the paper's equations, in this project's parameterisation):

- position: ``mu = k R (mu_i + d_mu) + T`` exactly as the paper;
- scale: the project stores log-scales, and the delta is added to the log:
  ``s = k exp(log s_i + d_s)``. The paper adds ``d_s`` to the linear scale, which can turn negative;
  in log space the scale stays positive with no clamp, and to first order ``exp(log s + d) = s + s d``;
- rotation: ``q = R (q_i + d_q)`` (normalised by the rasterizer), as the paper;
- colour: ``c = c_i + d_c`` on linear RGB, clamped at 0 like the SH evaluation (``colour_delta="add"``, the
  paper's); or ``c = c_i exp(d_c)`` (``colour_delta="scale"``): shading, a self-shadow, a crease or contact
  darkening multiply the albedo, so one factor serves every Gaussian whatever its colour;
- opacity: added to the logit, ``o = sigmoid(logit o_i + d_o)``, so it stays in (0, 1);
- interaction deltas are multiplied by ``w_i`` first.

The output layers start at zero, so before training the model renders exactly the warm-up model. The
number of Gaussians is fixed in this stage (no density control: the per-Gaussian point features and the
canonical positions stay aligned with their Gaussians).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from avatar.device import precision
from avatar.dynamic.conditioning import FrameConditioning
from avatar.geometry.frames import place_gaussians, place_means, triangle_frames
from avatar.nets.encoding import encoded_dim, positional_encoding
from avatar.nets.mlp import HEAD_KINDS, DeltaHeads, FixedProducts, SharedDeltaHeads, delta_heads
from avatar.nets.pointnet2 import PointNet2Encoder
from avatar.representations.bound.gaussians import SH_C0, BoundGaussians

HAND_GEO = {"mu": 3, "s": 3, "q": 4}
HAND_APP = {"c": 3, "o": 1}
INTERACTION = {"mu": 3, "s": 3, "q": 4, "c": 3, "o": 1}
_DISTANCE_CHUNK = 1024  # points per product with the targets (fits the cache)
COLOUR_DELTAS = ("add", "scale")  # how d_c enters the colour (DynamicModelConfig.colour_delta)
_MAX_LOG_SCALE = 10.0  # colour_delta="scale": exp(d_c) stays finite (e^10 is far beyond any shading)


@dataclass(frozen=True)
class DynamicModelConfig:
    """Architecture of the dynamic model (paper values as defaults; the quality presets shrink them).

    Attributes:
        hand_mlp / interaction: build H / I (False: the "w/o H" / "w/o I" ablations).
        hand_width, hand_depth: H's MLPs (paper: 256 units, 4 layers).
        interaction_width, interaction_depth: I's MLPs (paper: 256 units, 6 layers).
        position_frequencies: octaves of gamma(mu_cano) (NeRF uses 10 for positions); mu_cano is first
            normalised per part to the unit ball.
        offset_frequencies, offset_unit_m: gamma(d_j / offset_unit_m).
        point_feature_dim: width of P_i (paper: 64).
        geometry_feature_dim: width of F (paper: 1024).
        pointnet_centres, pointnet_radii, pointnet_neighbours: the two set-abstraction levels (radii in
            units of ``pointnet_unit_m``).
        pointnet_width: multiplier of the classic PointNet++ widths (64-64-128, 128-128-256, 256-512).
        pointnet_unit_m: metres per PointNet++ unit.
        d_max: interaction radius (paper: 0.05 m).
        deform_threshold_m: a face triangle deforms when its mean PBD offset exceeds this.
        colour_delta: how d_c enters: ``add`` (``c_i + d_c``, the paper) or ``scale`` (``c_i exp(d_c)``).
    """

    hand_mlp: bool = True  # H_geo, H_app on the hand Gaussians (false: the "w/o H" ablation)
    interaction: bool = True  # I on the face Gaussians near the hand (false: the "w/o I" ablation)
    hand_width: int = 256
    hand_depth: int = 4
    interaction_width: int = 256
    interaction_depth: int = 6
    position_frequencies: int = 10  # octaves of gamma(mu_cano) (NeRF)
    offset_frequencies: int = 4  # octaves of gamma(d_j / offset_unit_m)
    offset_unit_m: float = 0.01  # the unit of the PBD offsets d_j in I's encoding, metres
    point_feature_dim: int = 64  # P_i (paper)
    geometry_feature_dim: int = 1024
    pointnet_centres: tuple[int, int] = (512, 128)
    # ball radii of PointNet++'s two set-abstraction levels, units of pointnet_unit_m
    pointnet_radii: tuple[float, float] = (0.2, 0.4)
    pointnet_neighbours: tuple[int, int] = (32, 64)  # points grouped per centre at each level (PointNet++)
    pointnet_width: float = 1.0
    pointnet_unit_m: float = 0.1  # metres per PointNet++ unit
    d_max: float = 0.05  # interaction radius, metres (paper)
    deform_threshold_m: float = 1e-4  # a face triangle deforms (PointNet++ input) when its mean PBD offset exceeds this
    # d_c of H_app and I: add (c_i + d_c, the paper) or scale (c_i exp(d_c): shading multiplies); scale validated
    # 0.06 dB lower at draft (6 runs; docs/notes/2026-12-03-gains-with-seeds.md)
    colour_delta: str = "add"
    # the MLPs of H_geo, H_app and I: per_parameter (one MLP per Gaussian parameter, the paper) or shared (one trunk
    # per module with a linear head per parameter: the same inputs, zero deltas at the start, fewer products)
    heads: str = "per_parameter"

    def problems(self) -> list[str]:
        """Range problems of the settings that have a range beyond non-negative, one line each, keyed by field."""
        problems = []
        if self.colour_delta not in COLOUR_DELTAS:
            problems.append(
                f"colour_delta={self.colour_delta}: must be one of {', '.join(COLOUR_DELTAS)} "
                "(add: c_i + d_c as the paper; scale: c_i exp(d_c))"
            )
        if self.heads not in HEAD_KINDS:
            problems.append(
                f"heads={self.heads}: must be one of {', '.join(HEAD_KINDS)} (per_parameter: one MLP per Gaussian "
                "parameter, the paper; shared: one trunk per module)"
            )
        if not self.d_max > 0.0:
            problems.append(f"d_max={self.d_max:g}: must be positive (metres; the paper uses 0.05)")
        return problems

    @property
    def uses_geometry_feature(self) -> bool:
        return self.hand_mlp or self.interaction


@dataclass
class DynamicFrame:
    """The Gaussians of one frame, ready to rasterize, plus what the losses and counters need.

    Attributes:
        means, scales, quats: (N, 3), (N, 3), (N, 4) world space.
        opacities: (N,) in (0, 1); colors: (N, 3) linear RGB.
        local_means, local_scales: (N, 3) in the parent frame with the deltas (units of k), for L_mu, L_s.
        interaction_evaluations: Gaussians that went through I this frame.
    """

    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor
    local_means: Tensor
    local_scales: Tensor
    interaction_evaluations: int = 0


@dataclass(frozen=True)
class FixedInputs:
    """What a frozen :class:`DynamicAvatar`'s networks compute from the per-Gaussian inputs that no frame changes
    (:meth:`DynamicAvatar.fixed_inputs`): the products of the position code gamma(mu_cano) (and, for H_app, the point
    features P_i) by the columns of every MLP's input layer and skip. None for a module the model does not build.

    Attributes:
        hand_geo, hand_app: per MLP, (N_hand, width) products, the hand Gaussians in ``hand_index`` order.
        interaction: per MLP, (N_face, width) products of the position code alone (I's offset code changes with the
            frame), the face Gaussians in ``face_index`` order.
    """

    hand_geo: FixedProducts | None
    hand_app: FixedProducts | None
    interaction: FixedProducts | None


def interaction_weights(distance: Tensor, d_max: float) -> Tensor:
    """w = (cos(pi d / d_max) + 1) / 2 for d < d_max, else 0 (paper). distance: (N,) metres -> (N,)."""
    w = 0.5 * (torch.cos(math.pi * distance.clamp(0.0, d_max) / d_max) + 1.0)
    return torch.where(distance < d_max, w, torch.zeros_like(w))


def nearest_distance(points: Tensor, targets: Tensor, reach: float) -> Tensor:
    """(N,) distance of each of ``points`` (N, 3) to the nearest of ``targets`` (M, 3), exact where it is
    below ``reach`` and ``inf`` for points outside the targets' bounding box grown by ``reach``.

    ``torch.cdist(points, targets).min(-1).values`` to rounding (cdist's matrix-product form,
    ``[-2x, |x|^2, 1] . [y, 1, |y|^2]``, clamped at 1e-30, then the root), but the minimum is taken over the
    squared distances, before the clamp and the root (both monotonic), so the root is taken once per point
    and no indices are kept (a draft contact frame: 41 ms instead of 164)."""
    out = points.new_full((points.shape[0],), math.inf)
    if targets.shape[0] == 0 or points.shape[0] == 0:
        return out
    lo, hi = targets.min(0).values - reach, targets.max(0).values + reach
    near = ((points >= lo) & (points <= hi)).all(-1).nonzero()[:, 0]
    right = torch.cat([targets, torch.ones_like(targets[:, :1]), targets.pow(2).sum(-1, keepdim=True)], -1).mT
    for start in range(0, near.shape[0], _DISTANCE_CHUNK):
        idx = near[start : start + _DISTANCE_CHUNK]
        x = points[idx]
        left = torch.cat([x.mul(-2), x.pow(2).sum(-1, keepdim=True), torch.ones_like(x[:, :1])], -1)
        out[idx] = (left @ right).amin(-1).clamp_min_(1e-30).sqrt_()
    return out


def sample_one_per_triangle(
    weight: Tensor, triangle: Tensor, num_triangles: int, generator: torch.Generator | None
) -> Tensor:
    """Indices (P,) into ``weight`` (N,): one per triangle present in ``triangle`` (N,), drawn with
    probability proportional to ``weight`` among that triangle's entries (Gumbel-max: the argmax of
    ``log w + Gumbel noise``); with ``generator`` None the largest weight of each triangle."""
    key = weight.clamp_min(1e-30).log()
    if generator is not None:
        # drawn on the generator's device (the CPU's), so that a seed draws the same sample on every device
        u = (
            torch.rand(key.shape, generator=generator, dtype=key.dtype, device="cpu")
            .to(key.device)
            .clamp(1e-12, 1 - 1e-12)
        )
        key = key - torch.log(-torch.log(u))
    best = key.new_full((num_triangles,), -math.inf).scatter_reduce(0, triangle, key, "amax")
    winners = (key == best[triangle]).nonzero()[:, 0]
    # exact ties (measure zero when sampling; equal weights at evaluation): keep the first per triangle
    first = torch.full((num_triangles,), weight.shape[0], dtype=torch.long, device=key.device).scatter_reduce(
        0, triangle[winners], winners, "amin"
    )
    return first[first < weight.shape[0]]


def _normalise_per_part(points: Tensor, part: Tensor) -> Tensor:
    """(N, 3) points -> each part centred on its mean and scaled into the unit ball."""
    out = torch.zeros_like(points)
    for p in part.unique().tolist():
        sel = part == p
        centred = points[sel] - points[sel].mean(0)
        out[sel] = centred / centred.norm(dim=-1).max().clamp_min(1e-9)
    return out


class DynamicAvatar(nn.Module):
    """Warm-up Gaussians + point features + H + I + PointNet++ (see the module docstring).

    Args:
        gaussians: the warm-up model (trained further here).
        mu_cano: (N, 3) each Gaussian's world position on the canonical frame (see :meth:`from_warmup`).
        faces: (F, 3) the concatenated faces (face mesh first, then hand).
        part_names: mesh parts in the order of ``gaussians.part`` (must contain "face" and "hand").
        num_face_vertices: V_face, the face mesh's vertex count.
        frame_dims: widths of the conditioning: {"hand_pose", "expression"}.
        cfg: the architecture.
        seed: initialisation seed of the point features and the networks.
    """

    faces: Tensor  # buffers (register_buffer): (F, 3), (N, 3), (N, pe), (N_hand,), (N_face,)
    mu_cano: Tensor
    position_code: Tensor
    hand_index: Tensor
    face_index: Tensor
    hand_geo: DeltaHeads | SharedDeltaHeads | None  # None: the "w/o H" ablation (cfg.hand_mlp False), hand_app too
    hand_app: DeltaHeads | SharedDeltaHeads | None
    interaction: DeltaHeads | SharedDeltaHeads | None  # None: the "w/o I" ablation
    pointnet: PointNet2Encoder | None  # None when neither H nor I reads F

    def __init__(
        self,
        gaussians: BoundGaussians,
        mu_cano: Tensor,
        faces: Tensor,
        part_names: tuple[str, ...],
        num_face_vertices: int,
        frame_dims: dict[str, int],
        cfg: DynamicModelConfig,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        #: the networks' precision (``run.precision``): ``fp32``, or ``bf16`` (autocast; their outputs back in float32)
        self.precision = "fp32"
        self.gaussians = gaussians
        self.num_face_vertices = num_face_vertices
        self.face_part, self.hand_part = part_names.index("face"), part_names.index("hand")
        self.register_buffer("faces", faces.long())
        self.register_buffer("mu_cano", mu_cano.detach().clone())
        # gamma(mu_cano) is fixed in stage two: encoded once, derived again on load (not in the state dict)
        self.register_buffer(
            "position_code",
            positional_encoding(_normalise_per_part(self.mu_cano, gaussians.part), cfg.position_frequencies),
            persistent=False,
        )
        self.register_buffer("hand_index", (gaussians.part == self.hand_part).nonzero()[:, 0])
        self.register_buffer("face_index", (gaussians.part == self.face_part).nonzero()[:, 0])
        gen = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            self._build_networks(frame_dims, gen)

    @classmethod
    def from_warmup(
        cls,
        gaussians: BoundGaussians,
        canonical_vertices: Tensor,
        faces: Tensor,
        part_names: tuple[str, ...],
        num_face_vertices: int,
        frame_dims: dict[str, int],
        cfg: DynamicModelConfig,
        seed: int = 0,
    ) -> DynamicAvatar:
        """The model at the start of stage two: ``mu_cano`` from the warm-up Gaussians placed on
        ``canonical_vertices`` (V, 3), the first training frame (paper)."""
        with torch.no_grad():
            mu_cano, _, _ = gaussians.world(canonical_vertices, faces)
        return cls(gaussians, mu_cano, faces, part_names, num_face_vertices, frame_dims, cfg, seed)

    def network_state(self) -> dict[str, Tensor]:
        """The state dict without the Gaussians' own parameters (stored apart, as a table)."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("gaussians.")}

    def _build_networks(self, frame_dims: dict[str, int], gen: torch.Generator) -> None:
        cfg = self.cfg
        pe = encoded_dim(3, cfg.position_frequencies)
        F = cfg.geometry_feature_dim if cfg.uses_geometry_feature else 0
        hand, expr = frame_dims["hand_pose"], frame_dims["expression"]
        self.point_features = nn.Parameter(
            0.01 * torch.randn(self.hand_index.shape[0], cfg.point_feature_dim, generator=gen)
        )  # DeepSDF init
        self.hand_geo = (
            delta_heads(cfg.heads, HAND_GEO, pe, hand, cfg.hand_width, cfg.hand_depth) if cfg.hand_mlp else None
        )
        self.hand_app = (
            delta_heads(
                cfg.heads, HAND_APP, pe + cfg.point_feature_dim, F + hand + 6 + 6 + 3, cfg.hand_width, cfg.hand_depth
            )
            if cfg.hand_mlp
            else None
        )
        self.interaction = (
            delta_heads(
                cfg.heads,
                INTERACTION,
                pe + encoded_dim(3, cfg.offset_frequencies),
                F + hand + 12 + expr + 3 + 6,
                cfg.interaction_width,
                cfg.interaction_depth,
            )
            if cfg.interaction
            else None
        )
        self.pointnet = (
            PointNet2Encoder(
                feature_dim=F,
                centres=cfg.pointnet_centres,
                radii=cfg.pointnet_radii,
                neighbours=cfg.pointnet_neighbours,
                scale=cfg.pointnet_unit_m,
                width_multiplier=cfg.pointnet_width,
            )
            if cfg.uses_geometry_feature
            else None
        )

    # -- per-frame pieces --------------------------------------------------------------------------

    def triangle_offsets(self, cond: FrameConditioning) -> Tensor:
        """d_j (N_face, 3): mean PBD offset (head frame, metres) of each face Gaussian's parent triangle (the
        forward pass computes it once and hands it to :meth:`geometry_points` and the interaction)."""
        parent = self.faces[self.gaussians.binding[self.face_index]]  # (N_face, 3) vertex ids (< V_face)
        return cond.face_offsets[parent].mean(1)

    def geometry_points(
        self,
        cond: FrameConditioning,
        means: Tensor,
        scales: Tensor,
        opacities: Tensor,
        generator: torch.Generator | None,
        offsets: Tensor | None = None,
    ) -> Tensor:
        """PointNet++ input (P, 3), head frame: one Gaussian per deforming face triangle and per hand triangle,
        drawn with probability proportional to ``o ||s||`` (``generator`` None: the most probable one).
        ``offsets``: :meth:`triangle_offsets` of ``cond`` when already computed."""
        g = self.gaussians
        offsets = self.triangle_offsets(cond) if offsets is None else offsets
        deforming = offsets.norm(dim=-1) > self.cfg.deform_threshold_m
        candidates = torch.cat([self.face_index[deforming], self.hand_index])
        if candidates.numel() == 0:
            return means.new_zeros(0, 3)
        weight = opacities[candidates] * scales[candidates].norm(dim=-1)
        chosen = candidates[sample_one_per_triangle(weight, g.binding[candidates], self.faces.shape[0], generator)]
        return cond.to_head(means[chosen])

    def geometry_feature(self, points: Tensor) -> Tensor:
        """F (geometry_feature_dim,) from PointNet++ over ``points`` (P, 3); a learned vector when P = 0."""
        if self.pointnet is None:
            raise RuntimeError("this model reads no geometry feature (neither H nor I is built)")
        with precision(self.precision, points.device):
            return self.pointnet(points).float()

    @torch.no_grad()
    def fixed_inputs(self) -> FixedInputs:
        """The networks' products of the inputs no frame changes (:class:`FixedInputs`), for a model that is frozen
        from now on: :meth:`forward` given them computes the same frame, to rounding, without these products. They
        hold 2 x width floats per Gaussian and MLP (every MLP of H on the hand, of I on the face)."""
        code = self.position_code
        with precision(self.precision, code.device):
            return FixedInputs(
                hand_geo=None if self.hand_geo is None else self.hand_geo.fixed_products(code[self.hand_index]),
                hand_app=(
                    None
                    if self.hand_app is None
                    else self.hand_app.fixed_products((code[self.hand_index], self.point_features))
                ),
                interaction=(
                    None if self.interaction is None else self.interaction.fixed_products(code[self.face_index])
                ),
            )

    # -- the frame ---------------------------------------------------------------------------------

    def forward(
        self,
        cond: FrameConditioning,
        vertices: Tensor,
        generator: torch.Generator | None = None,
        fixed: FixedInputs | None = None,
    ) -> DynamicFrame:
        """The Gaussians of one frame.

        Args:
            cond: the frame's conditioning.
            vertices: (V, 3) the frame's posed mesh (face with its PBD offsets, then hand).
            generator: draws the PointNet++ sample (training); None takes the most probable (evaluation).
            fixed: :meth:`fixed_inputs` of this model as it is now (a frozen model posed many times), or None.
        """
        g = self.gaussians
        frames = triangle_frames(vertices, self.faces)
        local_means: Tensor  # the parameter, then the parameter plus its delta
        local_means, log_scales, quats = g.local_means, g.log_scales, g.quats
        logits, rgb = g.opacity_logits, 0.5 + SH_C0 * g.sh_dc
        deltas = {
            name: torch.zeros_like(x)
            for name, x in (("mu", local_means), ("s", log_scales), ("q", quats), ("o", logits[:, None]), ("c", rgb))
        }
        evaluations = 0
        feature = None
        if self.cfg.uses_geometry_feature:  # the Gaussians before any delta: PointNet++ input and w_i
            offsets = self.triangle_offsets(cond)
            with torch.no_grad():
                means0, scales0 = place_means(frames, g.binding, local_means, torch.exp(log_scales))
                points = self.geometry_points(cond, means0, scales0, torch.sigmoid(logits), generator, offsets)
            feature = self.geometry_feature(points)
        if self.hand_geo is not None:
            assert self.hand_app is not None and feature is not None  # built, and read, with H_geo
            idx = self.hand_index
            code = self.position_code[idx]
            frame = torch.cat([feature, cond.hand_pose, cond.hand_rotation, cond.rel_rotation, cond.rel_translation])
            with precision(self.precision, code.device):
                if fixed is None:
                    geo = self.hand_geo(code, cond.hand_pose)
                    app = self.hand_app((code, self.point_features), frame)
                else:  # every point input is in the products
                    geo = self.hand_geo((), cond.hand_pose, fixed.hand_geo)
                    app = self.hand_app((), frame, fixed.hand_app)
            for name, value in {**geo, **app}.items():
                deltas[name] = deltas[name].index_add(0, idx, value.float())
        if self.interaction is not None:
            assert feature is not None  # I reads F
            products = None if fixed is None else fixed.interaction
            evaluations = self._interact(cond, means0[self.face_index], offsets, vertices, feature, deltas, products)
        local_means = local_means + deltas["mu"]
        local_scales = torch.exp(log_scales + deltas["s"])
        means, scales, world_quats = place_gaussians(frames, g.binding, local_means, local_scales, quats + deltas["q"])
        return DynamicFrame(
            means=means,
            scales=scales,
            quats=world_quats,
            opacities=torch.sigmoid(logits + deltas["o"][:, 0]),
            colors=self._colour(rgb, deltas["c"]),
            local_means=local_means,
            local_scales=local_scales,
            interaction_evaluations=evaluations,
        )

    def _colour(self, rgb: Tensor, delta: Tensor) -> Tensor:
        """(N, 3) linear RGB from the Gaussians' own ``rgb`` (N, 3) and the summed deltas ``delta`` (N, 3)."""
        if self.cfg.colour_delta == "scale":
            return torch.clamp_min(rgb, 0.0) * torch.exp(torch.clamp_max(delta, _MAX_LOG_SCALE))
        return torch.clamp_min(rgb + delta, 0.0)

    def _interact(
        self,
        cond: FrameConditioning,
        face_means: Tensor,
        offsets: Tensor,
        vertices: Tensor,
        feature: Tensor,
        deltas: dict[str, Tensor],
        fixed: FixedProducts | None = None,
    ) -> int:
        """Add ``w_i I(...)`` of the face Gaussians near the hand to ``deltas``; returns how many ran I.
        ``face_means`` (N_face, 3): the face Gaussians' world means before any delta; ``offsets`` (N_face, 3):
        :meth:`triangle_offsets`; ``fixed``: :attr:`FixedInputs.interaction` (None: the position code multiplied
        here)."""
        assert self.interaction is not None  # called only when I is built
        idx = self.face_index
        with torch.no_grad():
            hand_vertices = vertices[self.num_face_vertices :]
            weight = interaction_weights(nearest_distance(face_means, hand_vertices, self.cfg.d_max), self.cfg.d_max)
        active = (weight > 0).nonzero()[:, 0]
        if active.numel() == 0:
            return 0
        offset_code = positional_encoding(offsets[active] / self.cfg.offset_unit_m, self.cfg.offset_frequencies)
        frame = torch.cat(
            [feature, cond.hand_pose, cond.face_pose, cond.expression, cond.rel_translation, cond.rel_rotation]
        )
        with precision(self.precision, offset_code.device):
            if fixed is None:
                outputs = self.interaction(torch.cat([self.position_code[idx[active]], offset_code], dim=-1), frame)
            else:  # the position code's products of the active Gaussians, then the offset code's
                outputs = self.interaction((offset_code,), frame, tuple(f.rows(active) for f in fixed))
        for name, value in outputs.items():
            deltas[name] = deltas[name].index_add(0, idx[active], weight[active, None] * value.float())
        return int(active.numel())
