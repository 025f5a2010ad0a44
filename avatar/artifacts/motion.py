"""The meshes a stage trains or renders on: the templates, a sequence posed with its parameters and, for methods
with PBD, the face deformed by the pbd stage's contact offsets."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from avatar.artifacts import load_face_offsets, load_params
from avatar.dynamic import sequence_conditioning
from avatar.dynamic.conditioning import Conditioning
from avatar.posing import MeshSequence, posed_meshes
from avatar.templates import TemplateModel, load_official_model, procedural_hand, procedural_head


def templates(model_cfg: DictConfig) -> tuple[TemplateModel, TemplateModel]:
    """(head, hand): the official FLAME/MANO files when configured, else the procedural templates."""
    head = load_official_model(model_cfg.flame_path, "flame") if model_cfg.flame_path else procedural_head()
    hand = load_official_model(model_cfg.mano_path, "mano") if model_cfg.mano_path else procedural_hand()
    return head, hand


def applied_deformation(cfg: DictConfig, pbd_dir: Path) -> Path | None:
    """``pbd_dir`` when the method deforms the face with the pbd stage's offsets (``method.pbd``), else
    ``None``: the "w/o PBD" ablation and the baselines pose undeformed meshes and give I ``d_j = 0``."""
    return pbd_dir if bool(cfg.method.pbd) else None


def load_sequence(
    fit_dir: Path, sequence: str, cfg: DictConfig, *, pbd_dir: Path | None, params: dict[str, np.ndarray] | None = None
) -> tuple[MeshSequence, Conditioning]:
    """Posed face + hand meshes of every frame of ``sequence`` from the fit stage's ``params.parquet`` (or from
    ``params``, e.g. a method's refined ones: :func:`method_params`), the face deformed by the pbd stage's contact
    offsets (``pbd_dir``; None: undeformed), and the dynamic model's conditioning of every frame."""
    posed = posed_sequence(fit_dir, sequence, cfg, pbd_dir, params)
    return posed.meshes, posed.conditioning(cfg)


@dataclass
class PosedSequence:
    """A sequence's parameters (the params.parquet columns), its posed meshes (the face's contact offsets added)
    and those offsets (T, V_face, 3) in metres (zeros without pbd)."""

    params: dict[str, np.ndarray]
    meshes: MeshSequence
    offsets: np.ndarray

    def conditioning(self, cfg: DictConfig) -> Conditioning:
        """The dynamic model's conditioning of every frame."""
        head, hand = templates(cfg.model)
        return sequence_conditioning(self.params, head, hand, torch.from_numpy(self.offsets))


def posed_sequence(
    fit_dir: Path, sequence: str, cfg: DictConfig, pbd_dir: Path | None, params: dict[str, np.ndarray] | None = None
) -> PosedSequence:
    """``sequence`` posed with ``params`` (default: the fit stage's) and the pbd stage's offsets (``pbd_dir``)."""
    head, _ = templates(cfg.model)
    params = load_params(fit_dir, sequence) if params is None else params
    num_frames = len(params["flame_global_orient"])
    if pbd_dir is None:
        return posed_with_offsets(params, cfg, np.zeros((num_frames, head.num_vertices, 3)))
    return posed_with_offsets(params, cfg, load_face_offsets(pbd_dir, sequence, num_frames, head.num_vertices))


def posed_with_offsets(params: dict[str, np.ndarray], cfg: DictConfig, offsets: np.ndarray) -> PosedSequence:
    """``params`` posed, the face's contact ``offsets`` (T, V_face, 3) (metres) added."""
    head, hand = templates(cfg.model)
    meshes = posed_meshes(params, head, hand)
    # posed_meshes concatenates the parts in order, face first: its vertices are the first V
    meshes.vertices[:, : head.num_vertices] += torch.from_numpy(offsets).to(meshes.vertices.dtype)
    return PosedSequence(params, meshes, offsets)
