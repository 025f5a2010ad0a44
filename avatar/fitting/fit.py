"""Multi-view FLAME/MANO fitting to 2D keypoints over a sequence.

Method (see :func:`fit_sequence`):

1. Triangulate every frame's hand keypoints and face landmarks (RANSAC DLT,
   :mod:`avatar.fitting.triangulation`); detections RANSAC rejects are dropped.
   From one camera (monocular), place each part's rest keypoints by PnP instead, at the depth its
   template's metric size implies (:mod:`avatar.fitting.monocular`).
2. Initialise each frame from the triangulated points: the hand by analytic
   inverse kinematics (:mod:`avatar.fitting.hand_ik`: palm by Kabsch, then each
   finger bone turned onto its observed direction), the face by rigid Kabsch
   alignment of the rest landmarks; frames without enough points copy the
   nearest good frame.
3. Optimise all frames at once with L-BFGS in float64 (translations in
   centimetres for conditioning): first the rigid parameters, then everything,
   under a confidence-weighted Geman-McClure reprojection loss (pixels) whose
   scale anneals from coarse to fine, weak L2 priors on pose, expression and
   shape (shape is shared by the sequence), a roughness prior on the identity
   where the template has one (the procedural head's landmark-region offsets),
   second-difference temporal
   smoothness and a hand-face interpenetration penalty
   (:mod:`avatar.fitting.penetration`, on the hand points near the face at the
   start of each phase). Keypoints come from keypoint-only templates
   (:mod:`avatar.templates.reduce`); full meshes are posed only for frames in
   contact.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from avatar.fitting.models import DTYPE, FaceParams, HandParams
from avatar.fitting.monocular import PALM, place_rest_points
from avatar.fitting.observations import PART_SIZES, Observations, pack_part
from avatar.fitting.penetration import ContactPairs, contact_depth, find_contact_pairs
from avatar.fitting.refine import Evidence, RefineConfig, RefineResult, refine_parameters
from avatar.fitting.rigid import MIN_RIGID_POINTS
from avatar.fitting.triangulation import projection_matrices, triangulate
from avatar.templates import TemplateModel
from data_schemas.cameras import Camera
from data_schemas.tables import SchemaError

MM_PER_M = 1000.0
#: stage.fit.identity_space: which identity columns of the head the face fit frees (:func:`face_shape_columns`)
IDENTITY_SPACES = ("auto", "full", "core")
#: keypoint detectors whose landmarks sit where the template's embedding puts them, up to noise (the synthetic
#: ground truth); identity_space=auto fits the full identity space only to these (docs/explanation/built-in-head.md).
UNBIASED_DETECTORS = ("ground_truth",)


@dataclass(frozen=True)
class FitConfig:
    """Fitting settings. Loss weights multiply terms that are averaged over frames;
    the data term is in px^2 per view (sum over keypoints)."""

    # triangulation: a detection farther than this (px) from the RANSAC point is an outlier
    ransac_threshold_px: float = 8.0
    min_confidence: float = 0.05  # detections below this confidence are not used
    min_views: int = 2  # views a keypoint needs to be triangulated (>= 2; a frame with fewer is weak)
    min_keypoints_per_view: int = 4  # confident keypoints of a part a view needs to count for that part's frame
    # scale of the robust (Geman-McClure) data term in the rigid and coarse steps (px)
    robust_scale_start_px: float = 20.0
    robust_scale_px: float = 8.0  # and in the fine steps (px)
    rigid_iterations: int = 30  # optimisation steps of the rotations and translations alone, first
    coarse_iterations: int = 120  # optimisation steps with a wide robust kernel (from the triangulated start)
    fine_iterations: int = 250  # steps with the final robust kernel
    hand_pose_prior: float = 1e-2  # L2 on MANO finger pose
    face_pose_prior: float = 1e-1  # L2 on neck/jaw/eye pose
    expression_prior: float = 1e-2  # L2 on expression coefficients
    shape_prior: float = 1e-2  # L2 on the shared shape coefficients
    # penalty on identity roughness (procedural head: landmark-region offsets unlike their neighbours')
    shape_roughness: float = 10.0
    face_shape_columns: int | None = None
    """Fit only the head's first ``face_shape_columns`` identity columns (None: all ``num_shape``); the
    result's ``flame_shape`` is that wide (the rest are zero)."""
    smooth_rotation: float = 1e-1  # second differences of rotations over time
    smooth_transl_mm: float = 1e-3  # second differences of translations (mm) over time
    penetration_mm: float = 1e-3  # hand-inside-face penalty (mm of penetration)
    penetration_stride: int = 4  # the interpenetration term checks every penetration_stride-th hand vertex
    penetration_radius_m: float = 0.03  # against the face within this distance of it (metres)


@dataclass
class FitResult:
    """A fitted sequence.

    Attributes:
        params: the column layout of :class:`avatar.synthetic.SyntheticCapture`
            (flame_* and mano_*), float64, T rows each, radians and metres.
        reprojection_px: part -> (T,) mean pixel distance between the fit's
            projections and the detections it used (NaN for a frame without any).
        weak_frames: part -> (T,) bool, frames with fewer than ``min_views``
            views holding ``min_keypoints_per_view`` confident keypoints, or fewer
            than 3 triangulated keypoints: the fit there leans on priors and
            neighbouring frames.
        timing: seconds per phase ("triangulation_s", "optimisation_s", "total_s")
            and "per_frame_per_view_ms".
        final_loss: total loss at the end of the keypoint optimisation.
        keypoint_params, keypoint_reprojection_px: ``params`` and ``reprojection_px`` of the keypoint fit
            before the image refinement (the same objects as those when there was none).
        refinement: what the image refinement did (None: none ran).
    """

    params: dict[str, np.ndarray]
    reprojection_px: dict[str, np.ndarray]
    weak_frames: dict[str, np.ndarray]
    timing: dict[str, float] = field(default_factory=dict)
    final_loss: float = float("nan")
    keypoint_params: dict[str, np.ndarray] = field(default_factory=dict)
    keypoint_reprojection_px: dict[str, np.ndarray] = field(default_factory=dict)
    refinement: RefineResult | None = None


def project(P: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Pixel projections (T, C, K, 2) of points (T, K, 3) through P (C, 3, 4);
    depth is clamped at 1 mm so points behind a camera stay finite."""
    hom = torch.cat((points, torch.ones_like(points[..., :1])), dim=-1)
    proj = torch.einsum("cij,tkj->tcki", P, hom)
    return proj[..., :2] / proj[..., 2:].clamp(min=1e-3)


def geman_mcclure(sq_err: torch.Tensor, scale: float) -> torch.Tensor:
    """Geman-McClure rho of squared residuals (px^2): ~e^2 for e << scale, -> scale^2 beyond."""
    return sq_err * scale**2 / (sq_err + scale**2)


def _data_term(
    P: torch.Tensor, points: torch.Tensor, obs: Observations, weight: torch.Tensor, scale: float
) -> torch.Tensor:
    sq = (project(P, points) - torch.as_tensor(obs.uv)).pow(2).sum(-1)
    return (weight * geman_mcclure(sq, scale)).sum() / (points.shape[0] * P.shape[0])


def _second_difference(x: torch.Tensor) -> torch.Tensor:
    """Mean squared second difference over time of (T, D) rows (0 for T < 3)."""
    if x.shape[0] < 3:
        return x.new_zeros(())
    return (x[2:] - 2 * x[1:-1] + x[:-2]).pow(2).sum() / x.shape[0]


def _mean_sq(x: torch.Tensor) -> torch.Tensor:
    return x.pow(2).sum() / x.shape[0]


def _regulariser(part: HandParams | FaceParams, cfg: FitConfig) -> torch.Tensor:
    """Pose, expression and shape priors plus temporal smoothness of one part."""
    if isinstance(part, HandParams):
        prior = cfg.hand_pose_prior * _mean_sq(part.hand_pose)
    else:
        prior = (
            cfg.expression_prior * _mean_sq(part.expression)
            + cfg.face_pose_prior * (_mean_sq(part.jaw_pose) + _mean_sq(part.neck_pose))
            + cfg.shape_roughness * part.roughness()
        )
    smooth = sum(_second_difference(x) for x in part.motion_terms())
    return (
        prior
        + cfg.shape_prior * part.shape.pow(2).sum()
        + cfg.smooth_rotation * smooth
        + cfg.smooth_transl_mm * _second_difference(part.transl * MM_PER_M)
    )


class _Problem:
    """The fitting objective over both parts of one sequence."""

    def __init__(
        self,
        hand: HandParams,
        face: FaceParams,
        P: torch.Tensor,
        obs: dict[str, Observations],
        weights: dict[str, torch.Tensor],
        cfg: FitConfig,
    ) -> None:
        self.hand, self.face, self.P, self.obs, self.weights, self.cfg = hand, face, P, obs, weights, cfg

    def _hand_points(self, hand_vertices: torch.Tensor) -> torch.Tensor:
        """(T, V, 3) -> the (T, N, 3) hand vertices checked for interpenetration."""
        return hand_vertices[:, :: self.cfg.penetration_stride]

    def loss(self, scale: float, pairs: ContactPairs | None) -> torch.Tensor:
        """The objective; ``pairs`` (hand points near the face) switch the penetration term on."""
        total = (
            _data_term(self.P, self.hand.keypoints(), self.obs["hand"], self.weights["hand"], scale)
            + _data_term(self.P, self.face.keypoints(), self.obs["face"], self.weights["face"], scale)
            + _regulariser(self.hand, self.cfg)
            + _regulariser(self.face, self.cfg)
        )
        if pairs is not None:
            frames, local = torch.unique(pairs.frame, return_inverse=True)  # pose only the frames in contact
            depth = contact_depth(
                self._hand_points(self.hand.vertices(frames)),
                self.face.vertices(frames),
                self.face.faces,
                pairs._replace(frame=local),
                self.cfg.penetration_radius_m,
            )
            total = total + self.cfg.penetration_mm * (depth * MM_PER_M).pow(2).sum() / self.hand.num_frames
        return total

    def _contact_pairs(self, penetration: bool) -> ContactPairs | None:
        """Hand points near the face at the current parameters (None: term off or no contact)."""
        if not penetration or self.cfg.penetration_mm <= 0:
            return None
        with torch.no_grad():
            pairs = find_contact_pairs(
                self._hand_points(self.hand.vertices()), self.face.vertices(), self.cfg.penetration_radius_m
            )
        return pairs if pairs.frame.numel() else None

    def minimise(self, params: list[torch.nn.Parameter], iterations: int, scale: float, penetration: bool) -> float:
        """L-BFGS (strong Wolfe) on ``params``; the others stay fixed. Contact pairs
        are found once at the start and held fixed. Returns the final loss."""
        everything = list(self.hand.parameters()) + list(self.face.parameters())
        for p in everything:
            p.requires_grad_(any(p is q for q in params))
        pairs = self._contact_pairs(penetration)
        opt = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=iterations,
            history_size=20,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-9,
            tolerance_change=1e-12,
        )

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = self.loss(scale, pairs)
            loss.backward()
            return loss

        if iterations > 0:
            opt.step(closure)
        for p in everything:
            p.requires_grad_(True)
        with torch.no_grad():
            return float(self.loss(scale, pairs))


#: How far apart the triangulated face landmarks may lie (metres: the largest distance between two of them,
#: median over frames). A human face spans about 0.14 m ear to ear, 0.08 m between the outer eye corners.
FACE_SPAN_M = (0.03, 1.0)


class WorldScaleError(ValueError):
    """The cameras' world units are not metres (the templates, the contact radius and PBD are)."""


def landmark_span(points: np.ndarray) -> float:
    """The largest distance between two of ``points`` (K, 3), K >= 1."""
    return float(np.linalg.norm(points[:, None] - points[None], axis=-1).max())


def check_world_scale(points: np.ndarray, valid: np.ndarray, template_span_m: float = 0.14) -> float | None:
    """The median over frames of the largest distance between two valid triangulated face landmarks
    (``points`` (T, K, 3), ``valid`` (T, K)); None where no frame has two. Raises
    :class:`WorldScaleError` when it lies outside :data:`FACE_SPAN_M`, with the scale that would make it
    ``template_span_m`` (the head template's own landmark span)."""
    spans = [landmark_span(p[v]) for p, v in zip(points, valid) if v.sum() >= 2]
    if not spans:
        return None
    span = float(np.median(spans))
    low, high = FACE_SPAN_M
    if not low <= span <= high:
        estimate = template_span_m / span
        raise WorldScaleError(
            f"the face landmarks triangulate {span:.4g} world units across, but a face spans about "
            f"{template_span_m:.2f} m: the camera translations are not in metres, which the templates, d_max and "
            f"PBD assume. Set dataset.calibration_scale_m={estimate:.3g} (metres per calibration unit, estimated "
            f"from the face's size against the head template's; heads differ by about 10 %, a distance measured "
            f"in the scene is better), or multiply the translations of world_to_cam by that factor and rerun"
        )
    return span


def _weak(obs: Observations, valid: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """(T,) frames with too few confident views or triangulated points."""
    confident = (obs.conf >= cfg.min_confidence).sum(-1) >= cfg.min_keypoints_per_view  # (T, C)
    return (confident.sum(-1) < min(cfg.min_views, confident.shape[1])) | (valid.sum(-1) < MIN_RIGID_POINTS)


def _triangulate_part(obs: Observations, P: np.ndarray, cfg: FitConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points (T, K, 3), valid (T, K) and per-detection weights (T, C, K) with
    RANSAC outliers of valid points set to zero."""
    points, valid, weight = [], [], obs.conf.copy()
    for t in range(obs.num_frames):
        uvc = np.concatenate((obs.uv[t], obs.conf[t][..., None]), axis=-1)
        tri = triangulate(uvc, P, cfg.min_views, cfg.ransac_threshold_px, cfg.min_confidence)
        points.append(tri.points)
        valid.append(tri.valid)
        weight[t] = np.where(tri.valid[None] & ~tri.inlier_mask, 0.0, weight[t])
    return np.stack(points), np.stack(valid), weight


def _reprojection_px(P: torch.Tensor, points: torch.Tensor, obs: Observations, weight: np.ndarray) -> np.ndarray:
    """(T,) mean pixel distance over the detections with non-zero weight (NaN where none)."""
    with torch.no_grad():
        dist = (project(P, points) - torch.as_tensor(obs.uv)).norm(dim=-1).numpy()
    used = weight > 0
    count = used.sum(axis=(1, 2))
    total = np.where(used, dist, 0.0).sum(axis=(1, 2))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def fit_sequence(
    keypoints: Mapping[str, Mapping[str, np.ndarray]],
    cameras: Sequence[Camera],
    head: TemplateModel,
    hand: TemplateModel,
    cfg: FitConfig | None = None,
    evidence: Evidence | None = None,
    refine: str = "none",
    refine_cfg: RefineConfig | None = None,
) -> FitResult:
    """Fit FLAME (``head``) and MANO (``hand``) to multi-view keypoints of a sequence.

    Args:
        keypoints: camera_id -> {"hand": (T, 21, 3), "face": (T, 68, 3)} rows of
            (u, v, confidence) in OpenCV pixels; NaN or zero confidence = missing.
            A camera may lack a part or be absent (no detections).
        cameras: the calibrated cameras to use (typically the train split).
        head, hand: the FLAME and MANO templates.
        cfg: settings and loss weights (defaults: :class:`FitConfig`).
        evidence, refine, refine_cfg: the training views' crops of the sequence, the mode and the settings of
            the image refinement that follows the keypoint fit (:mod:`avatar.fitting.refine`); none without
            evidence or with ``refine`` none.

    Returns:
        :class:`FitResult`; parameters are finite for any input.
    """
    cfg = cfg or FitConfig()
    unknown = set(keypoints) - {c.camera_id for c in cameras}
    if unknown:
        raise ValueError(f"keypoints for cameras not in the rig: {sorted(unknown)}")
    start = time.perf_counter()
    obs = {part: pack_part(keypoints, cameras, part, size) for part, size in PART_SIZES.items()}
    T = obs["hand"].num_frames
    P_np = projection_matrices(cameras)
    P = torch.as_tensor(P_np, dtype=DTYPE)
    hand_params, face_params = HandParams(hand, T), FaceParams(head, T, cfg.face_shape_columns)
    rest = {"hand": hand_params.rest_keypoints(), "face": face_params.rest_landmarks()[0]}
    weights, weak = {}, {}
    for part, model in (("hand", hand_params), ("face", face_params)):
        if len(cameras) == 1:  # monocular: placed by the template's metric size (avatar.fitting.monocular)
            points, valid = place_rest_points(
                rest[part],
                obs[part].uv[:, 0],
                obs[part].conf[:, 0],
                cameras[0],
                cfg.min_confidence,
                PALM if part == "hand" else None,
            )
            weight = obs[part].conf.copy()
        else:
            points, valid, weight = _triangulate_part(obs[part], P_np, cfg)
            if part == "face":
                check_world_scale(points, valid, landmark_span(rest["face"]))
        model.init_from_keypoints(points, valid)
        weights[part] = torch.as_tensor(weight)
        weak[part] = _weak(obs[part], valid, cfg)
    triangulated = time.perf_counter()

    problem = _Problem(hand_params, face_params, P, obs, weights, cfg)
    rigid = [hand_params.global_orient, hand_params.transl_cm, face_params.global_orient, face_params.transl_cm]
    everything = list(hand_params.parameters()) + list(face_params.parameters())
    problem.minimise(rigid, cfg.rigid_iterations, cfg.robust_scale_start_px, penetration=False)
    problem.minimise(everything, cfg.coarse_iterations, cfg.robust_scale_start_px, penetration=True)
    final_loss = problem.minimise(everything, cfg.fine_iterations, cfg.robust_scale_px, penetration=True)
    done = time.perf_counter()
    keypoint_params, keypoint_reprojection = _result(hand_params, face_params, P, obs, weights)
    params, reprojection, refinement = keypoint_params, keypoint_reprojection, None
    if evidence is not None and refine != "none":
        pairs = problem._contact_pairs(penetration=True)
        refinement = refine_parameters(
            hand_params,
            face_params,
            lambda: problem.loss(cfg.robust_scale_px, pairs),
            evidence,
            refine,
            refine_cfg or RefineConfig(),
        )
        params, reprojection = _result(hand_params, face_params, P, obs, weights)
    return FitResult(
        params=params,
        reprojection_px=reprojection,
        weak_frames=weak,
        final_loss=final_loss,
        keypoint_params=keypoint_params,
        keypoint_reprojection_px=keypoint_reprojection,
        refinement=refinement,
        timing={
            "triangulation_s": triangulated - start,
            "optimisation_s": done - triangulated,
            "refinement_s": 0.0 if refinement is None else refinement.seconds,
            "total_s": time.perf_counter() - start,
            "per_frame_per_view_ms": (done - start) * 1000.0 / max(T * len(cameras), 1),
        },
    )


def _result(
    hand_params: HandParams,
    face_params: FaceParams,
    P: torch.Tensor,
    obs: dict[str, Observations],
    weights: dict[str, torch.Tensor],
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The parameter columns and per-part reprojection errors (T,) at the parameters' current values."""
    with torch.no_grad():
        posed = {"hand": hand_params.keypoints(), "face": face_params.keypoints()}
    reprojection = {part: _reprojection_px(P, posed[part], obs[part], weights[part].numpy()) for part in obs}
    params = {**face_params.columns(), **hand_params.columns()}
    if not all(np.isfinite(v).all() for v in params.values()):
        raise FloatingPointError("fit produced non-finite parameters")
    return params, reprojection


def face_shape_columns(head: TemplateModel, identity_space: str, detector: str) -> int | None:
    """How many identity columns the face fit frees: all (None) for ``full``, the template's core space for
    ``core``, and for ``auto`` the full space only with an unbiased detector (:data:`UNBIASED_DETECTORS`): the
    procedural head's landmark-region offsets would follow a real detector's systematic offsets."""
    if identity_space not in IDENTITY_SPACES:
        raise SchemaError(f"stage.fit.identity_space={identity_space!r}: choose one of {IDENTITY_SPACES}")
    if identity_space == "full" or (identity_space == "auto" and detector in UNBIASED_DETECTORS):
        return None
    return None if head.num_core_shape is None else int(head.num_core_shape)
