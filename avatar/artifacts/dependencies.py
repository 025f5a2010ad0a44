"""What a stage's output depends on beyond its inputs: the user files it reads (source listers) and the settings its
configuration never reads (``unused_keys``: left out of its cache key)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from avatar.pbd.problem import unused_settings as unused_pbd_settings
from data_schemas.sources import SourceFiles

#: The ``model`` settings a stage that poses the templates reads: all of ``model`` but the face stiffness, which
#: only the stages that simulate contact read (pbd, and evaluate and reenact for methods with PBD). Such a
#: stage keys on these, so a new stiffness file reruns no fit.
TEMPLATE_KEYS = ("model.flame_path", "model.mano_path")
#: What ``model.face_stiffness_path`` may name (avatar.pbd.stiffness).
STIFFNESS_SUFFIXES = (".npy", ".npz")


def model_file_problems(cfg: DictConfig) -> list[str]:
    """``model.flame_path`` and ``model.mano_path`` set to something that is not a file, one line each (the
    ``checks`` of the first stage that poses the templates: found before any stage runs)."""
    return [
        f"model.{key}={path}: no such file; give the official {name} file or leave it unset (null) for the "
        "built-in procedural template"
        for key, name in (("flame_path", "FLAME generic_model.pkl"), ("mano_path", "MANO_RIGHT.pkl"))
        if (path := cfg.model.get(key)) and not Path(str(path)).is_file()
    ]


def stiffness_file_problems(cfg: DictConfig) -> list[str]:
    """``model.face_stiffness_path`` set to something that is not a ``.npy`` or ``.npz`` file (the pbd stage's
    ``checks``: found before any stage runs, not after the fit)."""
    path = cfg.model.get("face_stiffness_path")
    if not path:
        return []
    if Path(str(path)).suffix.lower() not in STIFFNESS_SUFFIXES:
        return [
            f"model.face_stiffness_path={path}: must be a .npy file of skin thicknesses (m) or a .npz with "
            "'thickness_m' or 'stiffness'; or leave it unset (null)"
        ]
    if not Path(str(path)).is_file():
        return [f"model.face_stiffness_path={path}: no such file; fix the path or leave it unset (null)"]
    return []


def model_files(cfg: DictConfig) -> list[Path]:
    """The official FLAME/MANO files the config names (``model.*_path``), for source hashing."""
    return [Path(p).resolve() for p in (cfg.model.flame_path, cfg.model.mano_path) if p and Path(p).is_file()]


def contact_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # the SourceLister signature
    """Source lister of stages that simulate contact: the official model files and the face stiffness file."""
    stiffness = cfg.model.get("face_stiffness_path")
    extra = [Path(stiffness).resolve()] if stiffness and Path(stiffness).is_file() else []
    return SourceFiles(Path("/"), tuple(model_files(cfg) + extra))


def model_sources(cfg: DictConfig, subject: str) -> SourceFiles:  # the SourceLister signature
    """Source lister of stages that pose the official models: a replaced model file reruns them."""
    return SourceFiles(Path("/"), tuple(model_files(cfg)))


def unused_solver_settings(cfg: DictConfig) -> tuple[str, ...]:
    """The ``stage.pbd.solver`` settings the chosen solver never reads (``unused_keys`` of the pbd stage)."""
    return tuple(f"stage.pbd.solver.{name}" for name in unused_pbd_settings(str(cfg.stage.pbd.solver.method)))


def unused_driving_settings(cfg: DictConfig) -> tuple[str, ...]:
    """What of ``stage.pbd.solver`` a stage that drives the avatar (:func:`drive`) never reads: all of it for a
    method without PBD (and the face stiffness), else the settings of the solvers not chosen."""
    return unused_solver_settings(cfg) if bool(cfg.method.pbd) else ("stage.pbd.solver", "model.face_stiffness_path")
