"""Scripted performances: keyframes for the head and the hand, and their timing.

A script is two keyframe tracks over normalised time in [0, 1]. Frames are
sampled evenly over [0, 1], so every frame count sees the same performance
(the first and last frames are hand-away, non-contact; the middle of the
script is a chain of contacts, so even 6 frames include contact frames).
Between two keys, parameters blend with a smoothstep (ease in / out).

The hand is keyed *relative to the face*: a named anchor on the face, a
stand-off along the anchor's normal (negative = pressed into the soft tissue),
a finger direction and tilt in the head frame, and articulation. The seeded
variation jitters times, angles, stand-offs and articulation slightly; it never
changes which keys are contacts.

:func:`stage_scene` restages a script for the captures without interaction
(the hand held off the face, or out of view).

Head frame: the FLAME frame before global rotation (x: subject's left, y: up,
z: forward). The hand is a right hand; it works on the subject's right (-x).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from avatar.synthetic.identity import MotionStyle


@dataclass(frozen=True)
class HeadKey:
    """Head pose and expression at one time.

    Attributes:
        time: normalised time in [0, 1].
        yaw_deg, pitch_deg, roll_deg: head rotation (yaw + turns to the subject's
            left, pitch + looks down, roll + tilts the top to the subject's right).
        jaw_deg: jaw opening.
        smile: expression coefficient of the smile component.
        brow: expression coefficient of the brow-raise component.
    """

    time: float
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    jaw_deg: float = 0.0
    smile: float = 0.0
    brow: float = 0.0


@dataclass(frozen=True)
class HandKey:
    """Hand placement and articulation at one time.

    Attributes:
        time: normalised time in [0, 1].
        anchor: face anchor the hand is placed against (a key of
            :data:`avatar.synthetic.face_anchors.DIRECTIONS`).
        standoff_m: distance of the hand's contact point from the anchor along
            the anchor normal, metres; negative presses into the face.
        finger_dir: (3,) desired finger direction, head frame.
        tilt_deg: rotation of the hand about its lateral axis through the
            contact point; positive lifts the fingers off the face (and brings
            the wrist closer), negative swings the wrist away.
        contact: "extreme" (the hand's first point along -normal) or a finger
            name whose tip makes the contact ("index", ...).
        curl: (5,) flexion per joint in radians, thumb .. pinky.
        spread: finger abduction in radians.
        shift_m: (3,) extra translation of the hand in the head frame (moving it
            off the face), metres.
    """

    time: float
    anchor: str
    standoff_m: float
    finger_dir: tuple[float, float, float] = (0.0, 1.0, 0.0)
    tilt_deg: float = 0.0
    contact: str = "extreme"
    curl: tuple[float, float, float, float, float] = (0.2, 0.15, 0.15, 0.15, 0.15)
    spread: float = 0.05
    shift_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Script:
    """Keyframe tracks of one performance (keys sorted by time, first at 0, last at 1)."""

    head: tuple[HeadKey, ...]
    hand: tuple[HandKey, ...]


_RELAXED = (0.25, 0.2, 0.25, 0.3, 0.35)
_AWAY_SHIFT = (0.0, -0.02, 0.10)
_POINT = (0.5, 0.0, 1.1, 1.2, 1.25)  # index extended, others folded
_FIST = (0.7, 1.0, 1.1, 1.15, 1.2)

TRAIN = Script(
    head=(
        HeadKey(0.00),
        HeadKey(0.20, yaw_deg=-12, pitch_deg=3, roll_deg=-4, smile=0.6),
        HeadKey(0.40, yaw_deg=-20, pitch_deg=6, roll_deg=-6, smile=1.0),
        HeadKey(0.60, yaw_deg=-6, pitch_deg=10, brow=0.8),
        HeadKey(0.80, yaw_deg=8, pitch_deg=2, jaw_deg=12),
        HeadKey(1.00, yaw_deg=4, jaw_deg=3, smile=0.3),
    ),
    hand=(
        HandKey(0.00, "cheek", 0.05, curl=_RELAXED, shift_m=_AWAY_SHIFT),
        HandKey(0.12, "cheek", 0.02, tilt_deg=8, curl=(0.2, 0.1, 0.1, 0.15, 0.2)),
        HandKey(0.20, "cheek", -0.008, finger_dir=(0.1, 1.0, 0.2), curl=(0.15, 0.05, 0.05, 0.1, 0.1), spread=0.12),
        HandKey(0.30, "cheek", -0.009, finger_dir=(0.15, 1.0, 0.25), curl=(0.3, 0.35, 0.3, 0.3, 0.35), spread=0.02),
        HandKey(0.42, "jaw", -0.006, finger_dir=(0.2, 1.0, 0.3), curl=(0.3, 0.2, 0.2, 0.25, 0.3), spread=0.08),
        HandKey(0.50, "chin", 0.02, finger_dir=(1.0, 0.1, 0.4), curl=(0.5, 0.6, 0.6, 0.6, 0.6)),
        HandKey(0.56, "chin", -0.005, finger_dir=(1.0, 0.1, 0.4), curl=(0.5, 0.7, 0.75, 0.8, 0.85)),
        HandKey(0.68, "chin", -0.006, finger_dir=(1.0, 0.0, 0.3), curl=(0.6, 0.8, 0.85, 0.9, 0.95)),
        HandKey(0.76, "mouth", -0.003, tilt_deg=-35, contact="index", curl=_POINT, spread=0.0),
        HandKey(
            0.84, "mouth", -0.004, finger_dir=(0.2, 1.0, 0.0), tilt_deg=-30, contact="index", curl=_POINT, spread=0.0
        ),
        HandKey(0.92, "mouth", 0.05, tilt_deg=-20, contact="index", curl=_RELAXED),
        HandKey(1.00, "cheek", 0.05, curl=_RELAXED, shift_m=_AWAY_SHIFT),
    ),
)

TEST = Script(
    head=(
        HeadKey(0.00, yaw_deg=5),
        HeadKey(0.25, yaw_deg=-8, pitch_deg=-4, roll_deg=5, brow=1.0),
        HeadKey(0.45, yaw_deg=-25, pitch_deg=2, smile=0.8),
        HeadKey(0.65, yaw_deg=10, pitch_deg=8, jaw_deg=6),
        HeadKey(0.85, yaw_deg=-5, pitch_deg=12, roll_deg=-3, smile=0.4),
        HeadKey(1.00, yaw_deg=-2),
    ),
    hand=(
        HandKey(0.00, "temple", 0.05, curl=_RELAXED, shift_m=(0.0, -0.03, 0.10)),
        HandKey(0.12, "temple", 0.02, finger_dir=(0.3, 1.0, -0.3), curl=(0.2, 0.1, 0.1, 0.1, 0.15)),
        HandKey(0.17, "temple", -0.004, finger_dir=(0.3, 1.0, -0.3), curl=(0.2, 0.1, 0.1, 0.1, 0.15)),
        HandKey(0.25, "temple", -0.004, finger_dir=(0.2, 1.0, -0.2), curl=(0.2, 0.1, 0.1, 0.1, 0.15), spread=0.2),
        HandKey(0.36, "cheek", -0.008, finger_dir=(0.0, 1.0, 0.1), curl=(0.1, 0.05, 0.05, 0.05, 0.1), spread=0.25),
        HandKey(0.46, "cheek", -0.007, finger_dir=(-0.2, 1.0, 0.2), curl=(0.4, 0.45, 0.4, 0.35, 0.3), spread=0.05),
        HandKey(0.54, "mouth", 0.015, finger_dir=(1.0, 0.3, 0.0), curl=(0.3, 0.2, 0.2, 0.2, 0.2)),
        HandKey(0.62, "mouth", -0.004, finger_dir=(1.0, 0.3, 0.0), curl=(0.3, 0.25, 0.25, 0.25, 0.25)),
        HandKey(0.72, "chin", -0.004, finger_dir=(1.0, -0.2, 0.2), curl=_FIST),
        HandKey(0.86, "chin", -0.006, finger_dir=(1.0, -0.1, 0.2), curl=_FIST, spread=0.0),
        HandKey(0.93, "chin", 0.04, finger_dir=(1.0, -0.1, 0.2), curl=(0.5, 0.6, 0.6, 0.6, 0.6)),
        HandKey(1.00, "cheek", 0.05, curl=_RELAXED, shift_m=(0.01, -0.03, 0.10)),
    ),
)

SCRIPTS = {"train": TRAIN, "test": TEST}


def frame_times(num_frames: int) -> np.ndarray:
    """(T,) normalised times of the frames, evenly spread over [0, 1]."""
    return np.linspace(0.0, 1.0, num_frames) if num_frames > 1 else np.array([0.5])


def bracket(key_times: np.ndarray, t: float) -> tuple[int, int, float]:
    """Keys (i, j) around time t and the eased blend weight of key j."""
    j = int(np.clip(np.searchsorted(key_times, t, side="right"), 1, len(key_times) - 1))
    i = j - 1
    span = key_times[j] - key_times[i]
    s = float(np.clip((t - key_times[i]) / span, 0.0, 1.0)) if span > 0 else 1.0
    return i, j, s * s * (3 - 2 * s)


def jitter(script: Script, rng: np.random.Generator, style: MotionStyle = MotionStyle()) -> Script:
    """Small seeded variation of a script (times keep their order; contact keys
    stay contacts; the end keys keep times 0 and 1), acted in ``style`` (the default acts it as written: the
    same draws, the same values)."""
    gain = style.jitter_gain

    def time(t: float) -> float:
        return t if t in (0.0, 1.0) else float(t + rng.uniform(-0.008, 0.008))

    def jitter_curl(c: tuple[float, float, float, float, float]) -> tuple[float, float, float, float, float]:
        c0, c1, c2, c3, c4 = (float(x + rng.normal(0, 0.04) * gain) for x in c)
        return c0, c1, c2, c3, c4

    head = tuple(
        replace(
            k,
            time=time(k.time),
            yaw_deg=k.yaw_deg * style.head_gain + rng.normal(0, 2.0) * gain,
            pitch_deg=k.pitch_deg * style.head_gain + rng.normal(0, 1.5) * gain,
            roll_deg=k.roll_deg * style.head_gain + rng.normal(0, 1.0) * gain,
        )
        for k in script.head
    )
    hand = tuple(
        replace(
            k,
            time=time(k.time),
            standoff_m=k.standoff_m + float(rng.uniform(-0.0008, 0.0008)) * (k.standoff_m < 0),
            tilt_deg=k.tilt_deg + rng.normal(0, 2.0) * gain,
            curl=jitter_curl(k.curl),
            spread=float(k.spread + rng.normal(0, 0.02) * gain),
        )
        for k in script.hand
    )
    return Script(head=head, hand=hand)


#: no_contact scene: every hand key's stand-off is raised to at least this (metres), measured from the hand's
#: first point along the anchor normal. Between keys the blended placement swings the hand up to ~0.035 m
#: closer (jaw -> chin of the train script), so the hand stays > 0.06 m from the face, beyond the paper's
#: interaction radius d_max = 0.05 m (0.067 m at the least over both scripts, subjects and two seeds), and within
#: ~0.10 m of it while the script holds it at the face. (0.11 m took the hand partly out of the smoke views.)
CLEARANCE_M = 0.10
#: face_only scene: every hand key's placement is shifted this far in the head frame (metres: 2 m below the
#: head), far outside every camera of the rig (and the key light's shadow map) whatever the head pose.
OUT_OF_VIEW_SHIFT_M = (0.0, -2.0, 0.0)


def stage_scene(script: Script, scene: str) -> Script:
    """The script as staged for ``scene`` (one of :data:`avatar.synthetic.capture.SCENES`).

    ``interaction`` returns the script itself. ``no_contact`` keeps the head track and the hand's
    articulation and orientation and holds the hand off the face: each key's contact point becomes the
    hand's extreme point along the anchor normal (so the hand's size and tilt are accounted for, not just a
    fingertip's position) and its stand-off at least :data:`CLEARANCE_M`. ``face_only`` keeps the
    articulation and moves every hand key by :data:`OUT_OF_VIEW_SHIFT_M`, out of view (finite parameters).
    """
    if scene == "no_contact":
        hand = tuple(replace(k, contact="extreme", standoff_m=max(k.standoff_m, CLEARANCE_M)) for k in script.hand)
    elif scene == "face_only":
        hand = tuple(replace(k, shift_m=OUT_OF_VIEW_SHIFT_M) for k in script.hand)
    else:
        return script
    return replace(script, hand=hand)
