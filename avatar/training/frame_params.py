"""Per-frame FLAME/MANO parameters refined jointly with the avatar (GaussianAvatars' fine-tuning of the tracking).

GaussianAvatars optimises every training frame's FLAME rotation, translation, neck, jaw, eye pose and expression
together with the Gaussians (learning rates 1e-5 for rotations and poses, 1e-6 for translations, 1e-3 for the
expression). :class:`FrameParams` does the same for the train motion's FLAME and MANO parameters: each training
step renders one frame, the loss's gradient reaches that frame's parameters through the posed meshes the
Gaussians are bound to, and :class:`FrameAdam` moves that frame's row only. The shapes (identity) stay as fitted;
the pbd stage's contact offsets stay as simulated on the fitted meshes (added to the refined face).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from avatar.device import host
from avatar.dynamic.conditioning import Conditioning, SequenceConditioning, conditioning_from_posed
from avatar.geometry.rotations import rotation_angle_deg
from avatar.posing import posed_keypoints, run_layers, template_layers
from avatar.templates import TemplateModel

#: learning-rate group -> the params.parquet columns it moves (the shapes are never refined)
REFINED_COLUMNS: dict[str, tuple[str, ...]] = {
    "rotation": ("flame_global_orient", "mano_global_orient"),
    "pose": ("flame_neck_pose", "flame_jaw_pose", "flame_eye_pose", "mano_hand_pose"),
    "translation": ("flame_transl", "mano_transl"),
    "expression": ("flame_expression",),
}


@dataclass
class ParamLearningRates:
    """Adam learning rates of the refined parameters, per group of :data:`REFINED_COLUMNS` (radians and metres
    per update of a frame). 0 holds a group as fitted. The defaults were chosen on the training views
    (benchmarks/bench_train_refine.py, docs/explanation/tracking-refinement.md): ten times GaussianAvatars'
    (:data:`GAUSSIAN_AVATARS_RATES`), centred, the largest whose loss on the withheld training frames stays within
    the validation seed spread. Also the type schema of ``stage.<warmup|dynamic>.params_lr`` (so not frozen)."""

    rotation: float = 1e-4  # FLAME and MANO global rotations (GaussianAvatars: 1e-5)
    pose: float = 1e-4  # neck, jaw, eyes, fingers (GaussianAvatars: 1e-5)
    translation: float = 1e-5  # FLAME and MANO translations (GaussianAvatars: 1e-6)
    expression: float = 1e-2  # FLAME expression (GaussianAvatars: 1e-3)

    def problems(self) -> list[str]:
        """Range problems, one line each, keyed relative to the block; empty when it can run."""
        return [
            f"{f.name}={getattr(self, f.name):g}: must be a finite learning rate >= 0 (0 holds the group)"
            for f in fields(self)
            if not (math.isfinite(getattr(self, f.name)) and getattr(self, f.name) >= 0)
        ]


#: GaussianAvatars' rates of the FLAME fine-tuning
GAUSSIAN_AVATARS_RATES = ParamLearningRates(rotation=1e-5, pose=1e-5, translation=1e-6, expression=1e-3)


class FrameAdam:
    """Adam over the rows of per-frame tensors (T, D): :meth:`step` ``(t)`` updates row ``t`` from its gradient
    and advances only that row's moments and step count, exactly as a separate Adam per frame would.

    A dense Adam on the whole (T, D) tensor (GaussianAvatars') keeps moving every frame it did not render, on the
    momentum of its earlier gradients; here a frame moves only when it is rendered.
    """

    def __init__(
        self,
        groups: Sequence[tuple[Tensor, float]],
        num_frames: int,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-15,
    ) -> None:
        self.groups = list(groups)
        self.betas, self.eps = betas, eps
        self.exp_avg = [torch.zeros_like(p) for p, _ in self.groups]
        self.exp_avg_sq = [torch.zeros_like(p) for p, _ in self.groups]
        self.steps = torch.zeros(num_frames, dtype=torch.long, device="cpu")  # counted on the host

    @torch.no_grad()
    def step(self, frame: int | slice, lr_scale: float = 1.0) -> None:
        """Update row ``frame`` of every parameter with a gradient, then clear the gradients; ``lr_scale``
        multiplies every group's rate for this update (a schedule). A slice of rows updates each of them as its own
        step would; they must have taken the same number of steps (frames refined in lockstep)."""
        beta1, beta2 = self.betas
        self.steps[frame] += 1
        counts = self.steps[frame].unique()
        if counts.numel() != 1:
            raise ValueError(f"rows {frame} have taken different numbers of steps ({counts.tolist()})")
        n = int(counts[0])
        for (p, lr), m, v in zip(self.groups, self.exp_avg, self.exp_avg_sq):
            if p.grad is None:
                continue
            g = p.grad[frame]
            m[frame].mul_(beta1).add_(g, alpha=1 - beta1)
            v[frame].mul_(beta2).addcmul_(g, g, value=1 - beta2)
            denom = (v[frame] / (1 - beta2**n)).sqrt_().add_(self.eps)
            p[frame] -= lr * lr_scale / (1 - beta1**n) * m[frame] / denom
            p.grad = None

    def state_dict(self) -> dict[str, Any]:
        return {
            "exp_avg": [m.clone() for m in self.exp_avg],
            "exp_avg_sq": [v.clone() for v in self.exp_avg_sq],
            "steps": self.steps.clone(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.exp_avg = [m.clone() for m in state["exp_avg"]]
        self.exp_avg_sq = [v.clone() for v in state["exp_avg_sq"]]
        self.steps = state["steps"].clone()


class FrameParams(nn.Module):
    """The T frames' FLAME/MANO parameters of a sequence, the refined columns trainable, and the posed meshes and
    dynamic-model conditioning of one frame from them.

    Args:
        params: the params.parquet columns, T rows each.
        head, hand: their templates.
        face_offsets: (T, V_face, 3) world-frame contact offsets added to the posed face (None: none).
        lrs: the learning rate of each group of :data:`REFINED_COLUMNS`.
        centred: keep the corrections' mean over the refined frames at zero (:meth:`step`).
        device: where the parameters, the templates and the offsets live (the training run's device).
    """

    face_offsets: Tensor  # buffer (T, V_face, 3)

    def __init__(
        self,
        params: Mapping[str, np.ndarray],
        head: TemplateModel,
        hand: TemplateModel,
        face_offsets: Tensor | None,
        lrs: ParamLearningRates,
        centred: bool = False,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__()
        self.centred = centred
        t = {k: torch.tensor(np.asarray(v), dtype=torch.float32, device=device) for k, v in params.items()}
        self.flame, self.mano = template_layers(t, head, hand)
        self.flame.to(device, torch.float32)  # the templates' float64 buffers, cast once instead of in every forward
        self.mano.to(device, torch.float32)
        refined = {c for columns in REFINED_COLUMNS.values() for c in columns}
        self.rows = nn.ParameterDict({k: nn.Parameter(v) for k, v in t.items() if k in refined})
        for k, v in t.items():
            if k not in refined:
                self.register_buffer(k, v)
        self.fixed = tuple(k for k in t if k not in refined)
        self.start = {k: v.clone() for k, v in t.items() if k in refined}  # the parameters as given
        num_frames = next(iter(t.values())).shape[0]
        offsets = torch.zeros(num_frames, head.num_vertices, 3) if face_offsets is None else face_offsets.float()
        offsets = offsets.to(device)
        self.register_buffer("face_offsets", offsets)
        self.optimizer = FrameAdam(
            [(self.rows[c], getattr(lrs, group)) for group, columns in REFINED_COLUMNS.items() for c in columns],
            num_frames,
        )

    @property
    def num_frames(self) -> int:
        return self.face_offsets.shape[0]

    def columns(self, frame: int | slice) -> dict[str, Tensor]:
        """Every column's row ``frame`` as (1, D), or its rows ``frame`` (a slice) as (B, D) (the refined ones
        differentiable)."""
        rows = frame if isinstance(frame, slice) else slice(frame, frame + 1)
        return {k: p[rows] for k, p in self.rows.items()} | {k: getattr(self, k)[rows] for k in self.fixed}

    def vertices(self, frame: int) -> Tensor:
        """(V_face + V_hand, 3) posed face (with its contact offsets) and hand of ``frame``, in the order of
        :func:`avatar.posing.posed_meshes`; differentiable in the refined parameters."""
        face, hand = run_layers(self.flame, self.mano, self.columns(frame))
        return torch.cat([face.vertices[0] + self.face_offsets[frame], hand.vertices[0]])

    @torch.no_grad()
    def conditioning(self, frame: int) -> Conditioning:
        """The dynamic model's inputs of ``frame`` from its current parameters (no gradient: the refinement moves
        the meshes; the networks' inputs follow it, as they follow the fit)."""
        t = self.columns(frame)
        face, hand = run_layers(self.flame, self.mano, t)
        return self._conditioning(t, face.joints, hand.joints, self.face_offsets[frame : frame + 1]).frame(0)

    def posed(self, frames: slice) -> tuple[Tensor, SequenceConditioning]:
        """The frames ``frames`` (B of them) posed from their current parameters by one run of the template layers:
        their vertices (B, V_face + V_hand, 3) as :meth:`vertices`, differentiable in the refined parameters, and
        their conditioning as :meth:`conditioning`, without gradient."""
        t = self.columns(frames)
        face, hand = run_layers(self.flame, self.mano, t)
        offsets = self.face_offsets[frames]
        vertices = torch.cat([face.vertices + offsets, hand.vertices], dim=1)
        return vertices, self._conditioning(t, face.joints.detach(), hand.joints.detach(), offsets)

    @staticmethod
    def _conditioning(
        t: Mapping[str, Tensor], face_joints: Tensor, hand_joints: Tensor, offsets: Tensor
    ) -> SequenceConditioning:
        """The conditioning of B frames from their columns ``t`` ((B, D) each), posed joints ((B, J, 3) each) and
        contact offsets (B, V_face, 3), with the columns detached: a row of a refined parameter taken without
        gradient is a view that still says it requires one, and a backward pass would differentiate the networks
        that read it for nothing."""
        columns = {k: v.detach() for k, v in t.items()}
        return conditioning_from_posed(columns, face_joints[:, 0], hand_joints[:, 0], offsets)

    def step(self, frame: int, frames: np.ndarray) -> None:
        """Move row ``frame`` by its gradient (:class:`FrameAdam`) and clear the gradients. ``centred``: then
        subtract the mean correction over ``frames`` (the frames training refines) from each of them.

        The Gaussians and the parameters together have a gauge freedom: moving every frame's mesh one way and the
        Gaussians' offsets the other renders the same images. Left free, the refinement drifts along it, and the
        frames it never refines (validation frames, the held-out motion), posed as fitted, no longer match the
        Gaussians. Centred, it corrects each frame relative to the others and leaves what all frames share, which
        the held-out motion's fit shares too, to the Gaussians."""
        self.optimizer.step(frame)
        if not self.centred or len(frames) == 0:
            return
        index = torch.as_tensor(np.asarray(frames), dtype=torch.long, device=self.face_offsets.device)
        with torch.no_grad():
            for k, p in self.rows.items():
                p[index] -= (p[index] - self.start[k][index]).mean(0)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every column as a (T, D) float32 array (the params.parquet columns)."""
        with torch.no_grad():
            return {k: host(v).copy() for k, v in self.columns_all().items()}

    def columns_all(self) -> dict[str, Tensor]:
        """Every column, all T frames."""
        return {**{k: p.detach() for k, p in self.rows.items()}, **{k: getattr(self, k) for k in self.fixed}}

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps to resume the refinement bit for bit."""
        return {"rows": {k: p.detach().clone() for k, p in self.rows.items()}, "optimizer": self.optimizer.state_dict()}

    def load_state(self, state: Mapping[str, Any]) -> None:
        with torch.no_grad():
            for k, value in state["rows"].items():
                self.rows[k].copy_(value)
        self.optimizer.load_state_dict(state["optimizer"])


def parameter_movement(
    before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray], head: TemplateModel, hand: TemplateModel
) -> dict[str, dict[str, np.ndarray]]:
    """How far each part moved from ``before`` to ``after`` (params.parquet columns, T rows each): ``moved_mm``
    part -> (T,) mean vertex displacement (mm) and ``rotated_deg`` part -> (T,) change of the global rotation
    (degrees); parts ``face`` and ``hand``."""
    posed = [posed_keypoints(p, head, hand) for p in (before, after)]
    moved = {
        part: 1e3 * np.linalg.norm(posed[1][f"{part}_vertices"] - posed[0][f"{part}_vertices"], axis=-1).mean(-1)
        for part in ("face", "hand")
    }
    rotated = {
        part: rotation_angle_deg(
            np.asarray(before[f"{prefix}_global_orient"], dtype=np.float64),
            np.asarray(after[f"{prefix}_global_orient"], dtype=np.float64),
        )
        for part, prefix in (("face", "flame"), ("hand", "mano"))
    }
    return {"moved_mm": moved, "rotated_deg": rotated}
