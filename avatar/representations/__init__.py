"""Gaussian representations as plug-ins: what the training stages train, and what evaluation, reenactment and the
PLY export pose and render, behind one interface (:class:`Representation`).

A method's YAML names its representation in ``method.representation``: a built-in name (:data:`BUILT_IN`:
``bound``, GaussianAvatars' Gaussians bound to the triangles, which InteractAvatar extends; ``embedded``,
SplattingAvatar's) or ``package.module:Class`` for a :class:`Representation` subclass defined anywhere on the
Python path. The stages only call the interface; nothing else branches on the representation
(docs/development/adding-a-method.md).
"""

from __future__ import annotations

import importlib
import json
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import ClassVar, Protocol, Self, runtime_checkable

import torch
from omegaconf import DictConfig

from avatar.artifacts import WorldGaussians, write_frame_ply
from avatar.artifacts.motion import PosedSequence
from avatar.artifacts.stage_run import StageRun
from avatar.dynamic.conditioning import SequenceConditioning
from avatar.geometry.views import ViewSet
from avatar.posing import MeshSequence
from avatar.training.avatar_tracking import PoseFrame
from avatar.training.frame_params import FrameParams
from avatar.training.settings import unused_section_settings
from avatar.training.validation import Validator
from data_schemas.tables import TableSchema
from data_schemas.writes import write_json

#: The representations that ship with the project: name -> ``module:Class``.
BUILT_IN = {
    "bound": "avatar.representations.bound.representation:BoundRepresentation",
    "embedded": "avatar.representations.embedded.representation:EmbeddedRepresentation",
}

#: The folder of a training stage's output that holds the model of its validated run when it trains again on every
#: frame afterwards (``validation.retrain``): stage two chooses with the warm-up's (docs/explanation/selection.md).
VALIDATED_RUN = "validation"

#: A training stage's progress bar over its steps (the training loops' ``progress``: wraps the steps, yields them).
Progress = Callable[[Iterable[int]], Iterator[int]]


class CanonicalGaussians(Protocol):
    """The warm-up's Gaussians on the canonical mesh (``avatar.representations.bound.gaussians.BoundGaussians``,
    ``avatar.representations.embedded.EmbeddedGaussians``): N Gaussians, each on one triangle of one mesh part."""

    @property
    def part(self) -> torch.Tensor:
        """(N,) mesh part index."""
        ...

    @property
    def opacity_logits(self) -> torch.Tensor:
        """(N,) opacity logits."""
        ...

    @property
    def num_gaussians(self) -> int: ...

    def world(self, vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World-space means (N, 3), scales (N, 3) and quaternions (N, 4) on the mesh ``vertices`` (V, 3)."""
        ...

    def set_colors(self, colors: torch.Tensor) -> None:
        """Set the RGB colours (N, 3) in [0, 1]."""
        ...

    def colors(self) -> torch.Tensor:
        """(N, 3) RGB in [0, 1]."""
        ...

    def opacities(self) -> torch.Tensor:
        """(N,) in (0, 1)."""
        ...

    def to(self, device: torch.device | str) -> Self:
        """These Gaussians on ``device`` (an ``nn.Module``'s ``to``)."""
        ...


class GaussianPopulation(Protocol):
    """A class of :class:`CanonicalGaussians` that populates a mesh's triangles."""

    def on_triangles(
        self,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        face_part: torch.Tensor,
        per_triangle: int,
        /,
        *,
        init_opacity: float = ...,
        seed: int = ...,
        populate: torch.Tensor | None = ...,
    ) -> CanonicalGaussians:
        """``per_triangle`` Gaussians on each triangle of the mesh ``vertices`` (V, 3), ``faces`` (F, 3) (``face_part``
        (F,) their parts), only on the triangles ``populate`` (F,) bool marks (None: all)."""
        ...


class TrainedAvatar(Protocol):
    """A method's final model, loaded from its dynamic stage's folder, frozen (no parameter of it requires a
    gradient: a pose may be differentiated in the vertices, e.g. to track a motion with the avatar)."""

    @property
    def num_gaussians(self) -> int: ...

    @property
    def triangles(self) -> torch.Tensor:
        """(N,) int64: the triangle (a row of the posed meshes' faces) each Gaussian rides on; the browser viewer
        poses the Gaussians with that triangle's frame (:mod:`avatar.viewer.codec`)."""
        ...

    def on_device(self, device: str, precision: str) -> TrainedAvatar:
        """This avatar on the torch ``device`` (``cpu``, ``cuda:N``), its networks (where it has any) run in
        ``precision`` (``fp32``, ``bf16``); on the CPU in fp32 the avatar as loaded."""
        ...

    def pose(self, cond: SequenceConditioning, vertices: torch.Tensor, frame: int) -> WorldGaussians:
        """The world-space Gaussians of frame ``frame`` of a sequence whose conditioning is ``cond`` and whose
        posed meshes of that frame have ``vertices`` (V, 3), as evaluated (no sampling noise)."""
        ...


@runtime_checkable
class PosesRepeatedly(Protocol):
    """A :class:`TrainedAvatar` that may offer a faster posing for many poses of the same avatar (optional)."""

    def frame_pose(self) -> PoseFrame:
        """As :func:`frame_pose`; what the avatar computes from inputs that no frame changes is computed here, once,
        and kept by the function it returns (the same Gaussians as :meth:`TrainedAvatar.pose`, to rounding)."""
        ...


def frame_pose(avatar: TrainedAvatar) -> PoseFrame:
    """One frame's world-space Gaussians of ``avatar`` as a function of that frame's conditioning and posed vertices
    (V, 3), for posing the same frozen avatar many times (tracking a motion by it): the avatar's own
    ``frame_pose()`` where it has one (:class:`PosesRepeatedly`), else its :meth:`~TrainedAvatar.pose` of a sequence
    of that one frame."""
    if isinstance(avatar, PosesRepeatedly):
        return avatar.frame_pose()
    return lambda cond, vertices: avatar.pose(cond.as_sequence(), vertices, 0)


class Representation(ABC):
    """A Gaussian representation: how the Gaussians are initialised on the mesh, trained in the two stages,
    saved, loaded and posed. One instance per run, built from the run's config (``cfg``)."""

    #: Config sections only this representation reads (its own recipe): in the training stages' cache keys when it is
    #: the method's, and only then (:func:`training_settings`).
    own_settings: ClassVar[tuple[str, ...]] = ()
    #: Whether the training stages may refine the train motion's parameters with it (``refine_params``).
    refines_tracking: ClassVar[bool] = True
    #: stage (``warmup``, ``dynamic``) -> (schema of its ``train_log.parquet``, the loss terms the report plots).
    train_logs: ClassVar[dict[str, tuple[TableSchema, tuple[str, ...]]]]
    #: The class of the Gaussians the warm-up populates the mesh with (BoundGaussians, EmbeddedGaussians).
    gaussians: ClassVar[GaussianPopulation]

    def __init__(self, cfg: DictConfig) -> None:
        self.cfg = cfg
        self.key = str(cfg.method.representation)  # as the method names it; model.json records it

    def problems(self) -> list[str]:
        """Settings of the run this representation cannot train with, one line each naming the key and the fix
        (checked with the rest of the config before any stage runs); empty when it can run."""
        return []

    def populate(
        self,
        canonical: torch.Tensor,
        meshes: MeshSequence,
        per_triangle: int,
        *,
        init_opacity: float,
        seed: int,
        populate: torch.Tensor | None,
    ) -> CanonicalGaussians:
        """The warm-up's initial Gaussians (:attr:`gaussians`): ``per_triangle`` on each triangle of the canonical
        mesh (``canonical`` (V, 3) with ``meshes.faces``), only on the triangles ``populate`` (F,) bool marks (None:
        all)."""
        return self.gaussians.on_triangles(
            canonical,
            meshes.faces,
            meshes.face_part,
            per_triangle,
            init_opacity=init_opacity,
            seed=seed,
            populate=populate,
        )

    @abstractmethod
    def warm_up(
        self,
        ctx: StageRun,
        model: CanonicalGaussians,
        views: ViewSet,
        meshes: MeshSequence,
        params: FrameParams | None,
        validator: Validator,
        progress: Progress,
        *,
        out_dir: Path,
        checkpoint_dir: Path | None,
    ) -> float:
        """Stage one: train ``model`` in place on ``views`` of the posed ``meshes`` for ``quality.warmup_steps``, on the
        frames and for the steps ``validator`` leaves to it (refining ``params``, the train motion's parameters,
        where not None); write ``gaussians.parquet`` and ``train_log.parquet`` to ``out_dir`` (the stage's output or
        its :data:`VALIDATED_RUN` folder), resuming from and saving checkpoints in ``checkpoint_dir``. Returns the
        final loss."""

    @abstractmethod
    def train(
        self, ctx: StageRun, views: ViewSet, posed: PosedSequence, validated: PosedSequence | None = None
    ) -> None:
        """Stage two on ``views`` of the train motion ``posed`` (posed with the warm-up's parameters), starting from
        the warm-up's ``gaussians.parquet`` (``ctx.input_dir("warmup")``); ``validated``: the train motion as the
        warm-up's validated run left it, where the warm-up kept one (:data:`VALIDATED_RUN`; stage two's own validated
        run starts from that model, which withheld the same frames). Write the dynamic stage's outputs
        (``gaussians.parquet``, ``networks.pt``, ``model.json`` through :func:`write_model_info`,
        ``train_log.parquet``, ``params.parquet``, ``ply/``) and its metrics."""

    @classmethod
    @abstractmethod
    def load(cls, dynamic_dir: Path, info: dict) -> TrainedAvatar:
        """The trained avatar of a dynamic stage's folder (``info``: its ``model.json``)."""


def run_scratch(ctx: StageRun, run: str) -> Path | None:
    """The checkpoint folder of one training run of a stage that trains more than once (``run``: its name; ``""``:
    the stage's scratch itself), created; None when the stage has no scratch."""
    if ctx.scratch_dir is None:
        return None
    folder = ctx.scratch_dir / run if run else ctx.scratch_dir
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def representation_class(name: str) -> type[Representation]:
    """The class ``method.representation`` names: a key of :data:`BUILT_IN` or ``package.module:Class``.
    ``ValueError`` naming the key and the choices otherwise."""
    target = BUILT_IN.get(name, name)
    choices = f"use one of {', '.join(BUILT_IN)}, or package.module:Class for a Representation of your own"
    module, sep, attribute = target.partition(":")
    if not sep or not module or not attribute:
        raise ValueError(f"method.representation={name}: unknown representation; {choices}")
    try:
        cls = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"method.representation={name}: cannot import {target} ({exc}); {choices}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Representation)):
        raise ValueError(
            f"method.representation={name}: {target} is not a subclass of avatar.representations.Representation"
        )
    return cls


def training_settings(cfg: DictConfig) -> tuple[str, ...]:
    """The config sections the training stages read for this method beyond their own: its representation's
    ``own_settings``, whichever representation it is (SplattingAvatar's recipe, ``splatting``, for ``embedded``; a
    plug-in's own section); none where ``method.representation`` names no representation (the config check says
    so)."""
    try:
        return representation_class(str(cfg.method.representation)).own_settings
    except ValueError:
        return ()


def _refines_tracking(cfg: DictConfig) -> bool:
    """Whether the method's representation may refine the train motion's parameters (true where it names none)."""
    try:
        return representation_class(str(cfg.method.representation)).refines_tracking
    except ValueError:  # the config check names it
        return True


def unused_warmup_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What the warm-up never reads of ``stage.warmup`` for this method (:func:`unused_section_settings`)."""
    return unused_section_settings(cfg, "warmup", _refines_tracking(cfg))


def unused_stage_two_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What stage two never reads of ``stage.dynamic``, nor of ``stage.warmup``, which its key holds too, for this
    method (:func:`unused_section_settings`)."""
    can_refine = _refines_tracking(cfg)
    return unused_section_settings(cfg, "warmup", can_refine) + unused_section_settings(cfg, "dynamic", can_refine)


def representation(cfg: DictConfig) -> Representation:
    """The method's representation (``method.representation``) for the run's config ``cfg``."""
    return representation_class(str(cfg.method.representation))(cfg)


def representation_problems(cfg: DictConfig) -> list[str]:
    """The method's representation's problems with ``cfg`` (an unknown name is one), one line each."""
    try:
        return representation(cfg).problems()
    except ValueError as exc:
        return [str(exc)]


MODEL_INFO = "model.json"


def write_model_info(out_dir: Path, rep: Representation, info: dict, what: str) -> None:
    """The dynamic stage's ``model.json``: ``info`` (what :meth:`Representation.load` needs) and the
    representation's key, which :func:`load_trained` finds the class by."""
    write_json(out_dir / MODEL_INFO, {"representation": rep.key, **info}, what)


def load_trained(dynamic_dir: Path) -> TrainedAvatar:
    """The method's final model from its dynamic stage's folder, by the representation its ``model.json`` names
    (``bound`` where it names none: artifacts written before the key existed)."""
    info = json.loads((dynamic_dir / MODEL_INFO).read_text())
    return representation_class(str(info.get("representation", "bound"))).load(dynamic_dir, info)


def write_train_plys(
    ctx: StageRun, avatar: TrainedAvatar, cond: SequenceConditioning, meshes: MeshSequence, num_frames: int
) -> None:
    """World-space 3DGS PLYs of the train frames ``stage.dynamic.ply_frames`` asks for (``ply/train_<frame>.ply``)."""
    (ctx.out_dir / "ply").mkdir()
    with torch.no_grad():
        for frame in sorted({min(max(int(f), 0), num_frames - 1) for f in ctx.cfg.stage.dynamic.ply_frames}):
            write_frame_ply(
                ctx.out_dir / "ply" / f"train_{frame}.ply", avatar.pose(cond, meshes.vertices[frame], frame)
            )
