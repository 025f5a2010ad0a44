"""Single-view initialisation: each part's rest keypoints placed in the world by PnP.

With one camera nothing can be triangulated, and depth is only observed through size. The prior a
monocular tracker uses is a known metric size: the template's rest landmarks (the head) and rest palm
(the wrist and the five finger bases, nearly rigid) are posed per frame by SQPnP against the detections,
so each part starts at the depth its template's size implies. The joint optimisation then refines the
articulation from the one view (:func:`avatar.fitting.fit.fit_sequence`), with the shape shared over the
sequence, temporal smoothness and the hand-face interpenetration term, as in the multi-view fit.
"""

from __future__ import annotations

import cv2
import numpy as np

from data_schemas.cameras import Camera

#: OpenPose indices of the palm: the wrist, the thumb's base and the four finger bases.
PALM = (0, 1, 5, 9, 13, 17)
MIN_PNP_POINTS = 4


def place_rest_points(
    rest: np.ndarray,
    uv: np.ndarray,
    conf: np.ndarray,
    camera: Camera,
    min_confidence: float,
    subset: tuple[int, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The rest points rigidly placed per frame so that they project onto the detections.

    Args:
        rest: (K, 3) the part's rest keypoints, metres.
        uv: (T, K, 2) detections in ``camera``'s OpenCV pixels; conf: (T, K) their confidences.
        camera: the one (undistorted) camera.
        min_confidence: detections below it are not used.
        subset: the points the pose is solved from (default all); all K are placed.

    Returns:
        points (T, K, 3) world metres and valid (T, K): a frame is valid where at least
        :data:`MIN_PNP_POINTS` usable detections of ``subset`` gave a pose in front of the camera.
    """
    T, K = conf.shape
    use_from = np.zeros(K, bool)
    use_from[list(subset) if subset is not None else slice(None)] = True
    points, valid = np.zeros((T, K, 3)), np.zeros((T, K), bool)
    cam_to_world = camera.cam_to_world
    for t in range(T):
        use = use_from & (conf[t] >= min_confidence) & np.isfinite(uv[t]).all(-1)
        if use.sum() < MIN_PNP_POINTS:
            continue
        ok, rvec, tvec = cv2.solvePnP(
            rest[use], uv[t, use].astype(np.float64), camera.K, None, flags=cv2.SOLVEPNP_SQPNP
        )
        if not ok or not np.isfinite(tvec).all():
            continue
        in_camera = (cv2.Rodrigues(rvec)[0] @ rest.T).T + tvec.ravel()
        if (in_camera[use, 2] <= 0).any():
            continue
        points[t] = in_camera @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
        valid[t] = True
    return points, valid
