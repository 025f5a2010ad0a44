"""Tracking refined by the images: the keypoint fit's per-frame FLAME/MANO parameters pulled onto what the
training views show of each frame.

The keypoint fit (:mod:`avatar.fitting.fit`) sees a few dozen 2D points per view; a detector's systematic
offsets and one camera's missing depth leave the meshes a centimetre or more from the skin. This module
renders the posed meshes and compares them with the frames stage's crops:

* ``silhouette``: the part silhouettes of the posed meshes, compared (squared error) with the crops' part
  labels, area-averaged to ``render_size``. Their values come from the exact z-buffer rasterizer, their
  gradients from one flat Gaussian per triangle (a disc in the triangle's plane, ``proxy_sigma`` times its
  frame scale k, see :mod:`avatar.geometry.frames`) coloured by its part on the project's differentiable
  rasterizer (see :class:`_Renderer` for why both). Pixels of an unknown foreground part compare nothing: on
  real footage that label is the rest of the person (keyed masks, MediaPipe's selfie segmentation: hair,
  neck, torso, arm), not a mesh's. Pixels no camera saw (crop padding) compare nothing either. Background
  pixels keep the meshes out, face and hand pixels pull them in: MediaPipe's face label (the hull of the face
  mesh) lies inside the head's silhouette, so it asks for coverage only where it is.
* ``photometric``: the silhouette term plus an L1 colour term: the meshes carry one colour per vertex, shared
  by every frame (an albedo, first fitted alone for ``colour_steps`` with the parameters held, learnt from the
  exact render), and the render over the capture's background colour is compared with the crops' colours.

The keypoint objective (reprojection, priors, temporal smoothness, interpenetration) stays in the loss as
the anchor. What moves: every frame's rotations, translations and articulation (FLAME: global rotation,
translation, neck, jaw, expression; MANO: global rotation, translation, finger pose); the shared shapes stay as
the keypoint fit left them. A part that no training view shows in a frame (no pixel of its label and no
unknown foreground) is left exactly as fitted in that frame: its gradients are masked there.

Image terms are in crop pixels (a term's value does not change with ``render_size``) and averaged over frames
and views, like the keypoint data term; Adam with per-group learning rates, decayed over the steps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from avatar.fitting.models import FaceParams, HandParams
from avatar.geometry.frames import place_gaussians, triangle_frames
from avatar.geometry.rotations import rotation_angle_deg
from avatar.geometry.views import UNOBSERVED_LABEL, ViewSet
from avatar.posing import posed_keypoints
from avatar.render.gaussians import render_gaussians
from avatar.render.mesh_raster import Mesh, PinholeCamera, box_downsample, interpolate, rasterize
from avatar.templates import TemplateModel

REFINE_MODES = ("none", "silhouette", "photometric")
PARTS = ("face", "hand")
#: crop labels of the parts (data_schemas.frames): 1 face, 2 hand, 3 foreground of unknown part
PART_LABELS = {"face": 1, "hand": 2}
UNKNOWN_LABEL = 3
#: :func:`tracking_outlines`' colours (RGB) of its parameter sets, in order: red, green, blue, yellow
OUTLINE_COLOURS: tuple[tuple[int, int, int], ...] = ((255, 64, 64), (64, 255, 64), (64, 160, 255), (255, 220, 64))
#: a part counts as seen in a frame when its label covers at least this many crop pixels in some training view
MIN_VISIBLE_PIXELS = 4.0


@dataclass
class RefineConfig:
    """Settings of the image refinement (``stage.fit.refinement``; the mode is ``stage.fit.refine``).

    Learning rates are Adam's per step, in the parameters' own units: radians (rotations, poses), centimetres
    (translations), expression coefficients, colour (linear RGB).
    """

    iterations: int = 100  # Adam steps over all frames and train views
    render_size: int = 64  # the crops are box-averaged to at most this many pixels per side for the comparison
    silhouette_weight: float = 1.0  # squared error of the part silhouettes (crop pixels, mean over frames and views)
    photometric_weight: float = 1.0  # photometric: L1 colour error (crop pixels, mean over frames and views)
    # the keypoint objective (reprojection, priors, smoothness, interpenetration) as anchor
    keypoint_weight: float = 0.1
    lr_rotation: float = 6e-3  # Adam step of the global rotations (rad)
    lr_translation_cm: float = 0.06  # of the translations (cm)
    lr_pose: float = 6e-3  # of the finger, neck and jaw poses (rad)
    lr_expression: float = 0.03  # of the expression coefficients
    lr_colour: float = 0.05  # photometric: of the per-triangle albedo
    lr_shape: float = 0.0  # of the shared identity coefficients (0: the keypoint fit's shapes stay)
    colour_steps: int = 40  # photometric: albedo-only steps before the tracking moves
    proxy_sigma: float = 0.35  # in-plane size of a triangle's proxy Gaussian (units of the triangle's scale k)
    proxy_opacity: float = 0.95  # opacity of the proxy Gaussians
    exact_every: int = 1  # steps between two exact (z-buffer) renders of every view, which correct the proxies' values


@dataclass
class Evidence:
    """What the training views show of a sequence, at the render size (T frames, C views, R x R pixels).

    Attributes:
        fractions: part -> (T, C, R, R) share of each render pixel the crop labels as that part ("face",
            "hand", "unknown" for foreground of unknown part).
        observed: (T, C, R, R) share of each render pixel the camera saw (not crop padding).
        colours: (T, C, R, R, 3) area-averaged crop colour in [0, 1].
        K: (C, 3, 3) intrinsics of the render (the crop's, scaled).
        world_to_cam: (C, 4, 4).
        background: (3,) the capture's background colour.
        pixel_area: crop pixels per render pixel (image terms are in crop pixels).
        visible: part -> (T,) bool, the part is seen by some view in that frame.
        camera_ids: the C camera names.
    """

    fractions: dict[str, Tensor]
    observed: Tensor
    colours: Tensor
    K: Tensor
    world_to_cam: Tensor
    background: Tensor
    pixel_area: float
    visible: dict[str, Tensor]
    camera_ids: list[str]

    @property
    def num_frames(self) -> int:
        return self.observed.shape[0]

    @property
    def num_cameras(self) -> int:
        return self.observed.shape[1]

    @property
    def size(self) -> int:
        return self.observed.shape[-1]


def downsample_factor(crop_size: int, render_size: int) -> int:
    """The smallest integer factor r that divides ``crop_size`` with ``crop_size / r <= render_size``."""
    r = max(1, math.ceil(crop_size / render_size))
    while crop_size % r:
        r += 1
    return r


def scaled_intrinsics(K: Tensor, r: int) -> Tensor:
    """(C, 3, 3) intrinsics of an image box-downsampled by ``r``, in the renderer's convention (pixel centres
    at integers): a render pixel j covers crop pixels r j .. r j + r - 1, centred at r j + (r - 1) / 2."""
    out = K.clone()
    out[:, :2, :2] /= r
    out[:, :2, 2] = (K[:, :2, 2] - (r - 1) / 2.0) / r
    return out


def _area_average(x: Tensor, r: int) -> Tensor:
    """(..., S, S) -> (..., S/r, S/r) box average."""
    if r == 1:
        return x
    lead = x.shape[:-2]
    y = F.avg_pool2d(x.reshape(-1, 1, *x.shape[-2:]), r)
    return y.reshape(*lead, *y.shape[-2:])


def evidence_from_views(views: ViewSet, render_size: int) -> Evidence:
    """The targets of the refinement from a sequence's training crops (:class:`ViewSet`)."""
    r = downsample_factor(views.size, render_size)
    labels = views.labels
    fractions = {part: _area_average((labels == label).float(), r) for part, label in PART_LABELS.items()}
    fractions["unknown"] = _area_average((labels == UNKNOWN_LABEL).float(), r)
    unknown_any = (labels == UNKNOWN_LABEL).flatten(2).sum(-1).amax(1) >= MIN_VISIBLE_PIXELS
    visible = {
        part: ((labels == label).flatten(2).sum(-1).amax(1) >= MIN_VISIBLE_PIXELS) | unknown_any
        for part, label in PART_LABELS.items()
    }
    colours = _area_average(views.images.float().permute(0, 1, 4, 2, 3) / 255.0, r).permute(0, 1, 3, 4, 2)
    return Evidence(
        fractions=fractions,
        observed=_area_average((labels != UNOBSERVED_LABEL).float(), r),
        colours=colours.contiguous(),
        K=scaled_intrinsics(views.K.double(), r).float(),
        world_to_cam=views.world_to_cam.float(),
        background=views.background.float(),
        pixel_area=float(r * r),
        visible=visible,
        camera_ids=list(views.camera_ids),
    )


def silhouette_error(rendered: Tensor, fractions: dict[str, Tensor], observed: Tensor) -> Tensor:
    """Per-pixel squared error (R, R) of a part render against the labels of one view; a pixel holding any
    unknown-part foreground compares nothing.

    Args:
        rendered: (R, R, 3) render of the part colours over black: channel 0 face, channel 1 hand coverage.
        fractions: part -> (R, R) labelled share ("face", "hand", "unknown").
        observed: (R, R) share of the pixel the camera saw.
    """
    per_part = (rendered[..., 0] - fractions["face"]).pow(2) + (rendered[..., 1] - fractions["hand"]).pow(2)
    return torch.where(fractions["unknown"] > 0, torch.zeros_like(per_part), per_part) * observed


@dataclass
class ProxyMeshes:
    """Both parts' faces with one proxy Gaussian per triangle.

    Attributes:
        faces: part -> (F_p, 3) int64 triangles of that part's mesh.
        local_scales: (3,) the proxy's scale in triangle units (in-plane, normal, in-plane).
    """

    faces: dict[str, Tensor]
    local_scales: Tensor

    def gaussians(self, vertices: Tensor, part: str) -> tuple[Tensor, Tensor, Tensor]:
        """Means (N, 3), quaternions (N, 4) and scales (N, 3) of the proxies on one posed mesh (V, 3)."""
        faces = self.faces[part]
        n = faces.shape[0]
        binding = torch.arange(n)
        means, scales, quats = place_gaussians(
            triangle_frames(vertices, faces),
            binding,
            vertices.new_zeros(n, 3),
            self.local_scales.to(vertices.dtype).expand(n, 3),
            vertices.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4),
        )
        return means, quats, scales


def proxy_meshes(face_faces: Tensor, hand_faces: Tensor, sigma: float) -> ProxyMeshes:
    """:class:`ProxyMeshes` of flat discs, ``sigma`` k wide and 5 % of that thick."""
    return ProxyMeshes(
        faces={"face": face_faces.long(), "hand": hand_faces.long()},
        local_scales=torch.tensor([sigma, 0.05 * sigma, sigma]),
    )


PART_COLOURS = {"face": (1.0, 0.0, 0.0), "hand": (0.0, 1.0, 0.0)}


@dataclass
class RefineResult:
    """What the refinement did.

    Attributes:
        seconds: wall time.
        losses: (iterations,) total loss per step.
        silhouette_iou: {"before"/"after": part -> camera_id -> IoU} of the exact mesh silhouettes (coverage
            > 0.5) against the labels (share > 0.5) at the render size, over the frames where the part is seen.
        moved_mm: part -> (T,) mean vertex displacement from the keypoint fit, mm.
        rotated_deg: part -> (T,) angle of the global rotation's change, degrees.
        frozen: part -> list of frames left as fitted (the part is seen by no training view there).
    """

    seconds: float
    losses: np.ndarray
    silhouette_iou: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    moved_mm: dict[str, np.ndarray] = field(default_factory=dict)
    rotated_deg: dict[str, np.ndarray] = field(default_factory=dict)
    frozen: dict[str, list[int]] = field(default_factory=dict)


#: samples per render pixel along each axis of the exact (z-buffer) silhouettes and colours
HARD_SUPERSAMPLE = 2


class _Renderer:
    """Renders both parts in every (frame, view) of :class:`Evidence`: the proxy Gaussians' renders, differentiable,
    plus a correction per view, the exact render (the z-buffer rasterizer, :mod:`avatar.render.mesh_raster`) minus
    the proxies' at the parameters of the last refresh (:meth:`loss`).

    A proxy disc bleeds past its triangle's edge by about its width: compared with the labels directly, the
    bleed makes every silhouette look a little too large, and the cheapest way to shrink it is to move the mesh
    away from the cameras (measured: the refined face ended 15 mm off, most of it depth). With the correction the
    loss's values are the exact meshes' wherever it was refreshed, so the refinement settles where the mesh
    silhouettes meet the labels; the proxies only say which way to move. Refreshing every few steps instead of
    every step (``exact_every``) saves the exact rasterizer's time, about that of a proxy render and its
    backward, at some accuracy (synth_a, every 4th step: 40 % less time, hand MPJPE 8.05 instead of 7.67 mm).
    """

    def __init__(self, hand: HandParams, face: FaceParams, evidence: Evidence, cfg: RefineConfig) -> None:
        self.hand, self.face, self.ev, self.cfg = hand, face, evidence, cfg
        self.proxies = proxy_meshes(face.faces, hand.layer.faces, cfg.proxy_sigma)
        self.counts = {p: self.proxies.faces[p].shape[0] for p in PARTS}
        self.corrections: list[list[Tensor]] = []  # per frame and view: exact minus proxy coverage (R, R, 2)
        self.cameras = [
            PinholeCamera(
                K=_mesh_raster_K(evidence.K[c]),
                world_to_cam=evidence.world_to_cam[c].double().numpy(),
                width=evidence.size,
                height=evidence.size,
            )
            for c in range(evidence.num_cameras)
        ]
        # the photometric albedo: one colour per vertex, shared by every frame, started at the mean foreground
        fg = evidence.fractions["face"] + evidence.fractions["hand"] + evidence.fractions["unknown"]
        weight = (fg * evidence.observed)[..., None]
        mean = (evidence.colours * weight).sum((0, 1, 2, 3)) / weight.sum().clamp_min(1e-6)
        self.num_vertices = {"face": face.layer.model.num_vertices, "hand": hand.layer.model.num_vertices}
        self.albedo = torch.nn.Parameter(mean.expand(sum(self.num_vertices.values()), 3).clone())

    def _posed(self) -> dict[str, Tensor]:
        return {"face": self.face.vertices(), "hand": self.hand.vertices()}

    def _albedo(self, part: str) -> Tensor:
        """(V_p, 3) the part's vertex colours."""
        return self.albedo[: self.num_vertices["face"]] if part == "face" else self.albedo[self.num_vertices["face"] :]

    def _shown(self, t: int) -> list[str]:
        return [p for p in PARTS if bool(self.ev.visible[p][t])]

    def _proxies(self, vertices: dict[str, Tensor], t: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(means, quats, scales, opacities, part colours) of the proxies of frame ``t``'s shown parts (float32)."""
        shown = self._shown(t)
        parts = [self.proxies.gaussians(vertices[p][t].float(), p) for p in shown]
        colours = [torch.tensor(PART_COLOURS[p]).expand(self.counts[p], 3) for p in shown]
        opacity = torch.full((sum(self.counts[p] for p in shown),), self.cfg.proxy_opacity)
        return (
            torch.cat([g[0] for g in parts]),
            torch.cat([g[1] for g in parts]),
            torch.cat([g[2] for g in parts]),
            opacity,
            torch.cat(colours),
        )

    def _proxy_albedo(self, t: int) -> Tensor:
        """(N, 3) each shown triangle's mean vertex albedo (detached: the albedo learns from the exact render)."""
        return torch.cat([self._albedo(p).detach()[self.proxies.faces[p]].mean(1) for p in self._shown(t)])

    def _exact(self, vertices: dict[str, Tensor], t: int, c: int, colour: bool) -> tuple[Tensor, Tensor | None]:
        """The exact part coverage (R, R, 2) of view ``c`` in frame ``t`` (no gradient) and, with ``colour``,
        its colours (R, R, 3) over the background (differentiable w.r.t. the albedo)."""
        shown = self._shown(t)
        meshes = [
            Mesh(
                vertices[p][t].detach(),
                self.proxies.faces[p],
                self._albedo(p) if colour else torch.zeros(self.num_vertices[p], 1),
                PART_LABELS[p],
            )
            for p in shown
        ]
        buffer, scene = rasterize(meshes, self.cameras[c], HARD_SUPERSAMPLE)
        coverage = torch.stack(
            [box_downsample((buffer.labels == PART_LABELS[p]).float(), HARD_SUPERSAMPLE) for p in PARTS], -1
        )
        if not colour:
            return coverage, None
        covered = buffer.covered
        samples = self.ev.background.expand(*covered.shape, 3)
        if covered.any():
            samples = samples.masked_scatter(covered[..., None], interpolate(buffer, scene))
        return coverage, box_downsample(samples, HARD_SUPERSAMPLE)

    def loss(self, silhouette_weight: float, photometric_weight: float, refresh: bool) -> Tensor:
        """The image terms summed over frames and views, in crop pixels, averaged over (frame, view).

        Silhouettes: the proxies' coverage plus each view's correction (exact minus proxy), recomputed when
        ``refresh`` (the first call with a silhouette term must refresh). Colours (photometric): the exact
        render's values and albedo gradient, the proxies' gradient for the geometry (the albedo learns from the
        exact colours, so it is rendered exactly every step)."""
        ev, R = self.ev, self.ev.size
        vertices = self._posed()
        total = vertices["face"].new_zeros(())
        silhouette, colour = silhouette_weight > 0, photometric_weight > 0
        refresh = refresh and silhouette
        black = torch.zeros(3)
        if refresh:
            self.corrections = [[] for _ in range(ev.num_frames)]
        for t in range(ev.num_frames):
            parts = self._proxies(vertices, t)
            albedo = self._proxy_albedo(t) if colour else None
            for c in range(ev.num_cameras):
                K, w2c = ev.K[c], ev.world_to_cam[c]
                exact_coverage, exact_rgb = self._exact(vertices, t, c, colour) if refresh or colour else (None, None)
                if silhouette:
                    coverage = render_gaussians(*parts, K, w2c, R, R, black).rgb[..., :2]
                    if refresh:
                        assert exact_coverage is not None  # _exact ran: refresh
                        self.corrections[t].append(exact_coverage - coverage.detach())
                    frac = {k: v[t, c] for k, v in ev.fractions.items()}
                    error = silhouette_error(coverage + self.corrections[t][c], frac, ev.observed[t, c])
                    total = total + silhouette_weight * error.sum()
                if colour:
                    assert albedo is not None and exact_rgb is not None  # both made when colour
                    proxy = render_gaussians(*parts[:4], albedo, K, w2c, R, R, ev.background).rgb
                    rgb = exact_rgb + (proxy - proxy.detach())
                    error = (rgb - ev.colours[t, c]).abs().sum(-1) * ev.observed[t, c]
                    total = total + photometric_weight * error.sum()
        return total * ev.pixel_area / (ev.num_frames * ev.num_cameras)

    @torch.no_grad()
    def silhouette_iou(self) -> dict[str, dict[str, float]]:
        """part -> camera_id -> IoU of the exact mesh silhouettes (coverage > 0.5) and the labels (share > 0.5)
        over the frames that show the part."""
        ev = self.ev
        vertices = self._posed()
        inter = {p: np.zeros(ev.num_cameras) for p in PARTS}
        union = {p: np.zeros(ev.num_cameras) for p in PARTS}
        for t in range(ev.num_frames):
            for c in range(ev.num_cameras):
                coverage, _ = self._exact(vertices, t, c, colour=False)
                seen = ev.observed[t, c] > 0.5
                for i, p in enumerate(PARTS):
                    if not bool(ev.visible[p][t]):
                        continue
                    pred, true = (coverage[..., i] > 0.5) & seen, (ev.fractions[p][t, c] > 0.5) & seen
                    inter[p][c] += float((pred & true).sum())
                    union[p][c] += float((pred | true).sum())
        return {
            p: {cam: float(inter[p][c] / union[p][c]) for c, cam in enumerate(ev.camera_ids) if union[p][c] > 0}
            for p in PARTS
        }


def _mesh_raster_K(K: Tensor) -> np.ndarray:
    """(3, 3) intrinsics of the renderer's convention (pixel centres at integers) in the z-buffer rasterizer's
    (pixel centres at integer + 0.5)."""
    out = K.double().numpy().copy()
    out[:2, 2] += 0.5
    return out


def _groups(hand: HandParams, face: FaceParams, cfg: RefineConfig) -> list[dict]:
    shapes = [{"params": [hand.shape, face.shape], "lr": cfg.lr_shape}] if cfg.lr_shape > 0 else []
    return shapes + [
        {"params": [hand.global_orient, face.global_orient], "lr": cfg.lr_rotation},
        {"params": [hand.transl_cm, face.transl_cm], "lr": cfg.lr_translation_cm},
        {"params": [hand.hand_pose, face.neck_pose, face.jaw_pose], "lr": cfg.lr_pose},
        {"params": [face.expression], "lr": cfg.lr_expression},
    ]


def _freeze_unseen(hand: HandParams, face: FaceParams, visible: dict[str, Tensor]) -> list:
    """Mask the per-frame gradients of a part in the frames no view shows it; returns the hook handles."""
    handles = []
    for part, model in (("hand", hand), ("face", face)):
        mask = visible[part].to(torch.float64)[:, None]
        for p in (model.global_orient, model.transl_cm, *model.pose_terms()):
            handles.append(p.register_hook(lambda g, m=mask: g * m))
    return handles


def refine_parameters(
    hand: HandParams, face: FaceParams, anchor: Callable[[], Tensor], evidence: Evidence, mode: str, cfg: RefineConfig
) -> RefineResult:
    """Refine ``hand`` and ``face`` (modified in place) against ``evidence``.

    Args:
        hand, face: the keypoint fit's parameters of T frames.
        anchor: the keypoint objective at the current parameters (a scalar tensor): reprojection, priors,
            smoothness, interpenetration.
        evidence: the training views' targets (:func:`evidence_from_views`), T frames.
        mode: ``silhouette`` or ``photometric`` (:data:`REFINE_MODES` but none).
        cfg: settings.
    """
    if mode not in REFINE_MODES[1:]:
        raise ValueError(f"refine mode {mode!r}: choose one of {REFINE_MODES[1:]}")
    if evidence.num_frames != hand.num_frames:
        raise ValueError(f"evidence of {evidence.num_frames} frames for parameters of {hand.num_frames}")
    start = time.perf_counter()
    renderer = _Renderer(hand, face, evidence, cfg)
    with torch.no_grad():
        before = {"face": face.vertices(), "hand": hand.vertices()}
        orient_before = {"face": face.global_orient.numpy().copy(), "hand": hand.global_orient.numpy().copy()}
    iou_before = renderer.silhouette_iou()
    photometric = cfg.photometric_weight if mode == "photometric" else 0.0
    movable = [p for g in _groups(hand, face, cfg) for p in g["params"]]
    if photometric > 0 and cfg.colour_steps > 0:  # the albedo first, with the tracking held
        for p in movable:
            p.requires_grad_(False)
        colour_opt = torch.optim.Adam([renderer.albedo], lr=cfg.lr_colour)
        for _ in range(cfg.colour_steps):
            colour_opt.zero_grad()
            renderer.loss(0.0, photometric, refresh=False).backward()
            colour_opt.step()
        for p in movable:
            p.requires_grad_(True)
    shapes = () if cfg.lr_shape > 0 else (hand.shape, face.shape)
    for p in shapes:
        p.requires_grad_(False)
    groups = _groups(hand, face, cfg)
    if photometric > 0:
        groups.append({"params": [renderer.albedo], "lr": cfg.lr_colour})
    opt = torch.optim.Adam(groups)
    decay = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * i / max(cfg.iterations, 1)))
    )
    handles = _freeze_unseen(hand, face, evidence.visible)
    losses = []
    try:
        for step in range(cfg.iterations):
            opt.zero_grad()
            loss = cfg.keypoint_weight * anchor() + renderer.loss(
                cfg.silhouette_weight, photometric, refresh=step % cfg.exact_every == 0
            )
            loss.backward()
            opt.step()
            decay.step()
            losses.append(float(loss.detach()))
    finally:
        for h in handles:
            h.remove()
        for p in shapes:
            p.requires_grad_(True)
    iou_after = renderer.silhouette_iou()
    with torch.no_grad():
        after = {"face": face.vertices(), "hand": hand.vertices()}
        orient_after = {"face": face.global_orient.numpy(), "hand": hand.global_orient.numpy()}
    return RefineResult(
        seconds=time.perf_counter() - start,
        losses=np.asarray(losses),
        silhouette_iou={"before": iou_before, "after": iou_after},
        moved_mm={p: 1e3 * (after[p] - before[p]).norm(dim=-1).mean(-1).numpy() for p in PARTS},
        rotated_deg={p: rotation_angle_deg(orient_before[p], orient_after[p]) for p in PARTS},
        frozen={p: np.flatnonzero(~evidence.visible[p].numpy()).tolist() for p in PARTS},
    )


def mesh_coverage(
    meshes: dict[str, Tensor], faces: dict[str, Tensor], K: Tensor, world_to_cam: Tensor, size: int
) -> Tensor:
    """(S, S) bool: the pixels (centres, renderer convention) that the posed ``meshes`` (part -> (V, 3)) cover
    in a view of intrinsics ``K`` (3, 3) and extrinsics ``world_to_cam`` (4, 4)."""
    camera = PinholeCamera(K=_mesh_raster_K(K), world_to_cam=world_to_cam.double().numpy(), width=size, height=size)
    scene = [Mesh(meshes[p], faces[p], torch.zeros(meshes[p].shape[0], 1), i + 1) for i, p in enumerate(meshes)]
    return rasterize(scene, camera, 1)[0].covered


def tracking_outlines(
    image: np.ndarray,
    K: Tensor,
    world_to_cam: Tensor,
    param_sets: Sequence[Mapping[str, np.ndarray]],
    frame: int,
    head: TemplateModel,
    hand: TemplateModel,
    with_hand: bool = True,
    colours: Sequence[tuple[int, int, int]] = OUTLINE_COLOURS,
) -> np.ndarray:
    """``image`` (S, S, 3) uint8 of one view (intrinsics ``K`` (3, 3), extrinsics ``world_to_cam`` (4, 4)), dimmed,
    with the outline of the face (and hand) mesh that each of ``param_sets`` (params.parquet columns, T rows) poses
    at ``frame``, in the matching RGB of ``colours`` (later sets on top). By default the first red, the second green
    (e.g. before and after a refinement), then :data:`OUTLINE_COLOURS`' blue and yellow."""
    if len(colours) < len(param_sets):
        raise ValueError(f"{len(param_sets)} parameter sets to outline but {len(colours)} colours")
    faces = {
        "face": torch.tensor(np.array(head.faces), dtype=torch.long),
        "hand": torch.tensor(np.array(hand.faces), dtype=torch.long),
    }
    masks = []
    for params in param_sets:
        posed = posed_keypoints({k: np.asarray(v)[frame : frame + 1] for k, v in params.items()}, head, hand)
        meshes = {"face": torch.as_tensor(posed["face_vertices"][0])}
        if with_hand:
            meshes["hand"] = torch.as_tensor(posed["hand_vertices"][0])
        masks.append(mesh_coverage(meshes, {p: faces[p] for p in meshes}, K, world_to_cam, image.shape[0]).numpy())
    return outline_overlay(image, masks, list(colours[: len(masks)]))


def outline_overlay(image: np.ndarray, masks: list[np.ndarray], colours: list[tuple[int, int, int]]) -> np.ndarray:
    """``image`` (S, S, 3) uint8, dimmed, with each of ``masks`` ((S, S) bool) drawn as its one-pixel outline
    in the matching colour (later masks on top)."""
    out = (image.astype(np.float32) * 0.6).astype(np.uint8)
    for mask, colour in zip(masks, colours):
        padded = np.pad(mask, 1, mode="edge")
        interior = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
        out[mask & ~interior] = colour
    return out
