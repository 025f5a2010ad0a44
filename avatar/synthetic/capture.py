"""What the synthetic generator is asked for and what it returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_schemas.cameras import Camera

#: The synthetic identities. synth_a and synth_b are the default dataset's two subjects; synth_c is a held-out third
#: identity (other head and hand proportions, a darker skin, a livelier performance) on which nothing is tuned.
SUBJECTS = ("synth_a", "synth_b", "synth_c")
SEQUENCES = ("train", "test")
#: What the capture shows (see :attr:`SyntheticConfig.scene`).
SCENES = ("interaction", "no_contact", "face_only")
#: How the skin's shading responds to pose and contact (see :attr:`SyntheticConfig.appearance`).
APPEARANCES = ("full", "plain", "pressed")


@dataclass(frozen=True)
class SyntheticConfig:
    """One synthetic capture.

    Attributes:
        subject: one of :data:`SUBJECTS` (identities: different FLAME/MANO shape, skin texture/colour and
            performance style).
        sequence: "train" or "test" (different motion; test is held out).
        image_size: square render resolution per camera, e.g. 64 (smoke) .. 512 (paper).
        num_frames: frames in the sequence, sampled evenly over the motion script.
        supersample: antialiasing samples per pixel along each axis.
        seed: varies the small random perturbations of the motion.
        num_cameras: cameras in the rig; one of them is the held-out 'test' view.
        performer: whose performance of the sequence's script (its random perturbations) the subject acts
            out; None: the subject's own. Another subject gives the ground truth of cross-actor
            reenactment: this identity performing the other's motion, the hand placed on this face as the
            script says.
        scene: what the capture shows, one of :data:`SCENES`. "interaction": the hand touches and dents the
            face. "no_contact": the same head motion and hand articulation, the hand held near the face
            (more than 0.06 m from it, beyond the paper's interaction radius of 0.05 m) and never touching
            it. "face_only": no hand in view; the ground-truth MANO parameters still follow the script's
            articulation but place the hand 2 m below the head, outside every camera (finite values, as
            the params schema wants every column). Both leave the face undeformed (zero face_offsets, no
            contact). See :func:`avatar.synthetic.motion.stage_scene`.
        appearance: one of :data:`APPEARANCES`. "full": finger creases that deepen with the bend, the curl
            self-shadow on the palm side and contact darkening of face and hand. "plain": none of the three (the
            albedo, lighting, shadows, geometry and dents are identical): pose and contact leave the skin's
            shading alone, so there is nothing for pose-dependent appearance to learn beyond the cast shadows.
            "pressed": "full" plus pressure blanching, what "full" lacks: skin pressed by a finger loses blood and
            turns paler and yellower in proportion to the dent's depth (a colour change, not a darkening).
    """

    subject: str
    sequence: str
    image_size: int
    num_frames: int
    supersample: int = 3
    seed: int = 0
    num_cameras: int = 8
    performer: str | None = None
    scene: str = "interaction"
    appearance: str = "full"

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f"scene must be one of {SCENES}, got {self.scene!r}")
        if self.appearance not in APPEARANCES:
            raise ValueError(f"appearance must be one of {APPEARANCES}, got {self.appearance!r} (dataset.appearance)")
        if self.subject not in SUBJECTS:
            raise ValueError(f"subject must be one of {SUBJECTS}, got {self.subject!r}")
        if self.performer is not None and self.performer not in SUBJECTS:
            raise ValueError(f"performer must be one of {SUBJECTS} or None, got {self.performer!r}")
        if self.sequence not in SEQUENCES:
            raise ValueError(f"sequence must be one of {SEQUENCES}, got {self.sequence!r}")
        if self.image_size < 8 or self.num_frames < 1 or self.supersample < 1:
            raise ValueError(f"need image_size >= 8, num_frames >= 1, supersample >= 1: {self}")


@dataclass
class SyntheticCapture:
    """A multi-view recording with ground truth (all arrays in memory).

    Attributes:
        cameras: the calibrated rig (OpenCV conventions, see :mod:`avatar.synthetic.rig`).
        frames: camera_id -> (T, H, W, 3) uint8 sRGB images (linear light through
            the sRGB OETF, see :mod:`avatar.synthetic.shading`), plain grey background.
        masks: camera_id -> (T, H, W) uint8 labels: 0 background, 1 face/head, 2 hand.
        params: per-frame ground truth, T rows each: flame_shape (T, S),
            flame_expression (T, E), flame_global_orient (T, 3), flame_neck_pose (T, 3),
            flame_jaw_pose (T, 3), flame_eye_pose (T, 6), flame_transl (T, 3),
            mano_shape (T, 10), mano_hand_pose (T, 45), mano_global_orient (T, 3),
            mano_transl (T, 3); float64, radians and metres.
        keypoints: camera_id -> {"hand": (T, 21, 3), "face": (T, L, 3)} rows of
            (u, v, visible) in OpenCV pixel coordinates;
            visible = 1 if inside the image and not occluded, else 0.
        face_offsets: (T, V_face, 3) soft-tissue displacement added to the posed
            FLAME vertices, world metres; zero away from contact.
        contact: (T,) bool, frames where the hand touches (dents) the face.
        frame_rate: frames per second of the sequence.
    """

    cameras: list[Camera]
    frames: dict[str, np.ndarray]
    masks: dict[str, np.ndarray]
    params: dict[str, np.ndarray]
    keypoints: dict[str, dict[str, np.ndarray]]
    face_offsets: np.ndarray
    contact: np.ndarray
    frame_rate: float
