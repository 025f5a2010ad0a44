"""Orchestration: identity + script -> posed meshes -> soft tissue -> shading ->
multi-view images, masks and keypoints (:func:`generate`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatar.render.mesh_raster import Mesh, render
from avatar.synthetic.appearance import HandAppearance, contact_occlusion, face_appearance, pressure_blanching
from avatar.synthetic.capture import SEQUENCES, SUBJECTS, SyntheticCapture, SyntheticConfig
from avatar.synthetic.face_anchors import FaceAnchors
from avatar.synthetic.face_paint import FacePaint
from avatar.synthetic.geometry import vertex_normals
from avatar.synthetic.hand_pose import HandFrame
from avatar.synthetic.identity import Identity, make_identity, motion_style
from avatar.synthetic.keypoints import FACE_SELF_TOLERANCE_M, HAND_SELF_TOLERANCE_M, project_keypoints
from avatar.synthetic.motion import SCRIPTS, frame_times, jitter, stage_scene
from avatar.synthetic.performance import Performance, perform
from avatar.synthetic.rig import make_rig, mesh_raster_camera
from avatar.synthetic.shading import BACKGROUND_LINEAR, Channels, ShadowMap, make_shader, srgb_encode
from avatar.synthetic.soft_tissue import contact_offsets
from avatar.templates.head import NUM_DESIGNED_SHAPE
from avatar.templates.layers import FLAMELayer, MANOLayer
from avatar.templates.procedural import procedural_hand, procedural_head
from avatar.threads import single_threaded

#: Nominal frame rate: frames sample the whole script whatever their number, so
#: fewer frames mean a faster-moving (time-compressed) performance.
FRAME_RATE = 30.0
FACE_LABEL = 1
HAND_LABEL = 2
#: The hand's texture coordinates are shifted so its noise differs from the face's.
HAND_TEXTURE_SHIFT = np.array([10.0, 0.0, 0.0])
#: Where the rig aims, relative to the centre of the rest face's landmarks (metres).
AIM_OFFSET = np.array([-0.02, -0.015, 0.0])


@dataclass(frozen=True)
class _Subject:
    """Template layers and static appearance of one identity."""

    identity: Identity
    flame: FLAMELayer
    mano: MANOLayer
    face_faces: np.ndarray  # (Ff, 3)
    hand_faces: np.ndarray  # (Fh, 3)
    face_rest: np.ndarray  # (Vf, 3) template positions (texture space)
    face_albedo: np.ndarray  # (Vf, 3)
    face_pores: np.ndarray  # (Vf,)
    face_paint: FacePaint
    hand_rest: np.ndarray  # (Vh, 3) template positions (texture space)
    hand: HandAppearance
    inner_distance: np.ndarray  # (Vf,) metres


def _subject(name: str) -> _Subject:
    head, hand = procedural_head(), procedural_hand()
    identity = make_identity(name, NUM_DESIGNED_SHAPE)  # the subjects lie in the designed identity space
    flame = FLAMELayer(head, NUM_DESIGNED_SHAPE, head.num_shapes_total - head.num_identity_shape)
    mano = MANOLayer(hand)
    rest = mano(torch.as_tensor(identity.mano_shape[None]), torch.zeros(1, 45, dtype=torch.float64))
    hand_rest, joints = rest.vertices[0].numpy(), rest.joints[0].numpy()
    albedo, pores = face_appearance(head, identity)
    return _Subject(
        identity=identity,
        flame=flame,
        mano=mano,
        face_faces=np.array(head.faces),
        hand_faces=np.array(hand.faces),
        face_rest=np.array(head.v_template),
        face_albedo=albedo,
        face_pores=pores,
        face_paint=FacePaint.build(flame, identity),
        hand_rest=np.array(hand.v_template),
        hand=HandAppearance.build(hand, identity, HandFrame.from_joints(joints), hand_rest, joints),
        inner_distance=np.array(head.inner_distance),
    )


def _attributes(
    rest: np.ndarray, world: np.ndarray, faces: np.ndarray, albedo: np.ndarray, occlusion: np.ndarray, pores: np.ndarray
) -> np.ndarray:
    """(V, Channels.COUNT) float32 per-vertex attributes for the shader."""
    normals = vertex_normals(torch.as_tensor(world), torch.as_tensor(faces)).numpy()
    attrs = np.zeros((rest.shape[0], Channels.COUNT), dtype=np.float32)
    attrs[:, Channels.CANONICAL] = rest
    attrs[:, Channels.WORLD] = world
    attrs[:, Channels.NORMAL] = normals
    attrs[:, Channels.ALBEDO] = albedo
    attrs[:, Channels.OCCLUSION] = occlusion
    attrs[:, Channels.PORES] = pores
    return attrs


def _scene(
    subject: _Subject,
    face: np.ndarray,
    hand: np.ndarray,
    hand_pose: np.ndarray,
    curl: np.ndarray,
    dent: np.ndarray,
    appearance: str = "full",
) -> list[Mesh]:
    """Face (label 1) and hand (label 2) meshes of one frame with shading attributes.

    Args:
        face: (Vf, 3) deformed face; hand: (Vh, 3) posed hand (world metres);
        hand_pose: (45,) MANO pose; curl: (5,) finger curl controls;
        dent: (Vf,) depth of each face vertex's soft-tissue offset (metres);
        appearance: see :attr:`SyntheticConfig.appearance` ("plain": no pose or contact shading).
    """
    if appearance == "plain":
        face_occ, hand_occ = np.ones(face.shape[0]), np.ones(hand.shape[0])
    else:
        face_occ, hand_occ = contact_occlusion(face, hand)
        bend = np.linalg.norm(hand_pose.reshape(15, 3), axis=1)
        hand_occ = hand_occ * subject.hand.pose_occlusion(curl, bend)
    face_albedo = pressure_blanching(subject.face_albedo, dent) if appearance == "pressed" else subject.face_albedo
    face_attrs = _attributes(subject.face_rest, face, subject.face_faces, face_albedo, face_occ, subject.face_pores)
    hand_attrs = _attributes(
        subject.hand_rest + HAND_TEXTURE_SHIFT,
        hand,
        subject.hand_faces,
        subject.hand.albedo,
        hand_occ,
        subject.hand.pores,
    )
    return [
        Mesh(face, subject.face_faces, face_attrs, FACE_LABEL),
        Mesh(hand, subject.hand_faces, hand_attrs, HAND_LABEL),
    ]


def _soft_tissue(subject: _Subject, perf: Performance) -> np.ndarray:
    """(T, Vf, 3) soft-tissue offsets of every frame."""
    inner = torch.as_tensor(subject.inner_distance)
    hand_faces, face_faces = torch.as_tensor(subject.hand_faces), torch.as_tensor(subject.face_faces)
    return np.stack(
        [
            contact_offsets(torch.as_tensor(face), face_faces, inner, torch.as_tensor(hand), hand_faces).numpy()
            for face, hand in zip(perf.face_vertices, perf.hand_vertices)
        ]
    )


def _aim_point(subject: _Subject) -> np.ndarray:
    """(3,) world point the cameras look at: near the rest face's centre, biased
    towards the hand side and down."""
    shape = torch.as_tensor(subject.identity.flame_shape[None])
    expression = torch.zeros(1, subject.flame.num_expression, dtype=torch.float64)
    verts = subject.flame(shape, expression).vertices
    return subject.flame.landmarks(verts)[0].numpy().mean(axis=0) + AIM_OFFSET


def generate(cfg: SyntheticConfig) -> SyntheticCapture:
    """Render the synthetic capture described by ``cfg`` (deterministic)."""
    with single_threaded():
        return _generate(cfg)


def _generate(cfg: SyntheticConfig) -> SyntheticCapture:
    subject = _subject(cfg.subject)
    performer = cfg.performer or cfg.subject
    rng = np.random.default_rng([cfg.seed, SUBJECTS.index(performer), SEQUENCES.index(cfg.sequence)])
    script = stage_scene(jitter(SCRIPTS[cfg.sequence], rng, motion_style(performer)), cfg.scene)
    perf = perform(
        script,
        frame_times(cfg.num_frames),
        subject.identity,
        subject.flame,
        subject.mano,
        FaceAnchors.build(subject.flame),
    )
    offsets = _soft_tissue(subject, perf)
    faces = perf.face_vertices + offsets
    aim = _aim_point(subject)
    cameras = make_rig(cfg.num_cameras, cfg.image_size, aim)
    t_count, size = cfg.num_frames, cfg.image_size
    frames = {c.camera_id: np.zeros((t_count, size, size, 3), np.uint8) for c in cameras}
    masks = {c.camera_id: np.zeros((t_count, size, size), np.uint8) for c in cameras}
    hand_kp = subject.mano.keypoints21(torch.as_tensor(perf.hand_vertices), torch.as_tensor(perf.hand_joints)).numpy()
    face_kp = subject.flame.landmarks(torch.as_tensor(faces)).numpy()
    keypoints = {
        c.camera_id: {
            "hand": np.zeros((t_count, hand_kp.shape[1], 3)),
            "face": np.zeros((t_count, face_kp.shape[1], 3)),
        }
        for c in cameras
    }
    background = (BACKGROUND_LINEAR,) * 3
    for t in range(t_count):
        meshes = _scene(
            subject,
            faces[t],
            perf.hand_vertices[t],
            perf.params["mano_hand_pose"][t],
            perf.curl[t],
            np.linalg.norm(offsets[t], axis=1),
            cfg.appearance,
        )
        shader = make_shader(
            ShadowMap.build(meshes, aim), subject.identity.texture_seed, {FACE_LABEL: subject.face_paint}
        )
        for cam in cameras:
            out = render(meshes, mesh_raster_camera(cam), cfg.supersample, background, shader, cull_backfaces=True)
            cid = cam.camera_id
            frames[cid][t] = srgb_encode(out.rgb.numpy())
            masks[cid][t] = out.labels.numpy().astype(np.uint8)
            depth = out.depth.numpy()
            keypoints[cid]["hand"][t] = project_keypoints(
                cam, hand_kp[t], depth, masks[cid][t], HAND_LABEL, HAND_SELF_TOLERANCE_M
            )
            keypoints[cid]["face"][t] = project_keypoints(
                cam, face_kp[t], depth, masks[cid][t], FACE_LABEL, FACE_SELF_TOLERANCE_M
            )
    contact = np.abs(offsets).reshape(t_count, -1).max(axis=1) > 0
    return SyntheticCapture(
        cameras=cameras,
        frames=frames,
        masks=masks,
        params=perf.params,
        keypoints=keypoints,
        face_offsets=offsets,
        contact=contact,
        frame_rate=FRAME_RATE,
    )
