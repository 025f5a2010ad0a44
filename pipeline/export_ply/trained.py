"""The trained run an export reads: found from ``--method`` and ``--seed``, checked against its manifests as the
pipeline's own plan judges it, its settings taken from them, and locked while it is read.

A run is exported only as the pipeline would keep it: every artifact it is computed from is whole and still computed
from what is on disk now (:func:`pipeline.runner.recorded_plan`). A fit republished after the model was trained
(``run.until=fit`` with another ``fit.source``) would otherwise be posed with a model trained on another fit; the
export names the command that trains the model again instead.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from avatar.reenact import PLACEMENTS
from data_schemas.names import folder_name_problem
from pipeline.config import changed_keys, fix_command, group_options
from pipeline.export_ply.options import LOCK_WAIT_S, ExportError
from pipeline.manifest import MANIFEST_NAME, Manifest, sha256_file
from pipeline.registry import StageRegistry, load_registry
from pipeline.runner import RecordedArtifact, recorded_plan
from pipeline.workspace import METHODS_DIR, Artifact, LockTimeout, Workspace, method_run, run_overrides, seed_problem

#: the DAG the runs were computed by (``pipeline.stages_module`` of the app's own stages)
STAGES_MODULE = "stages"
#: the stage whose artifact is the trained model
MODEL_STAGE = "dynamic"
#: the stages whose artifacts an export reads: their files are checked against their manifests, and the manifests
#: of every stage the model is computed from are checked
READS = ("fit", "scene", "pbd", MODEL_STAGE)
#: the official template files a run may have been posed with (``model.<key>``), by the template they hold
TEMPLATES = {"flame_path": "FLAME", "mano_path": "MANO"}
_ABSENT = object()


@dataclass
class TrainedRun:
    """A subject's trained method run on disk: its folders, the settings its stages ran with (``model``,
    ``method.pbd``, ``stage.pbd.solver``, from their manifests) plus ``reenact.placement`` for driver files, and the
    output digest of each artifact the export reads, by artifact id (``fit``, ``dynamic@<run>``)."""

    subject_dir: Path
    run: str
    cfg: DictConfig
    read: dict[str, str] = field(default_factory=dict)

    @property
    def dynamic_dir(self) -> Path:
        return self.subject_dir / METHODS_DIR / self.run / MODEL_STAGE

    @property
    def fit_dir(self) -> Path:
        return self.subject_dir / "fit"

    def motions(self) -> list[str]:
        """The motions of the fit (its sequences: ``train``, ``test``, a synthetic capture's ``cross_<subject>``)."""
        return sorted(p.parent.name for p in self.fit_dir.glob("*/params.parquet"))


@contextmanager
def open_run(
    subject_dir: Path,
    method: str = "interactavatar",
    seed: int = 0,
    *,
    placement: str = "contact",
    flame_path: str | None = None,
    mano_path: str | None = None,
    lock_wait_s: float = LOCK_WAIT_S,
) -> Iterator[TrainedRun]:
    """:func:`trained_run`, with the read locks of its artifacts and of those they are computed from held for the
    ``with`` block, as a running stage holds its inputs': no run replaces one while the block reads it. A run that is
    writing one now is waited for ``lock_wait_s`` seconds, then :class:`ExportError`. Where no lock file can be made
    (an outputs folder on a read-only disk, or another user's), the run is read without."""
    ws, target = _workspace(subject_dir, method, seed)
    registry = load_registry(STAGES_MODULE)
    with ExitStack() as locks:
        reads = _computed_from(registry, target)
        try:
            locks.enter_context(ws.lock(target, reads, registry.names(), lock_wait_s, write=False))
        except LockTimeout as exc:
            what = str(exc).partition("; ")[0]  # "stage 'pbd' of subject 'synth_a' is locked by another run (...)"
            raise ExportError(f"{what}, which is writing it; export again once that run has finished") from exc
        except OSError:
            pass  # no lock file can be made there: read without
        yield trained_run(subject_dir, method, seed, placement=placement, flame_path=flame_path, mano_path=mano_path)


def trained_run(
    subject_dir: Path,
    method: str = "interactavatar",
    seed: int = 0,
    *,
    placement: str = "contact",
    flame_path: str | None = None,
    mano_path: str | None = None,
) -> TrainedRun:
    """The trained run of ``method`` (seed ``seed``) under the subject folder ``subject_dir``, unlocked
    (:func:`open_run` locks it); :class:`ExportError` when there is none (naming the command that trains it where the
    pipeline would run that command), when the pipeline would compute it or anything it is computed from again, or
    when a template file is not the one it was posed with. ``flame_path``/``mano_path`` replace the official files the
    run recorded (moved since)."""
    ws, target = _workspace(subject_dir, method, seed)
    plan = {r.artifact.stage: r for r in recorded_plan(ws, load_registry(STAGES_MODULE), target, verify=READS)}
    stale = [r for r in plan.values() if r.stale is not None]
    if stale:
        raise ExportError(_stale_run(subject_dir, target, stale, plan))
    pbd, dynamic = (_manifest(plan[name]) for name in ("pbd", MODEL_STAGE))
    cfg = _settings(pbd, dynamic, placement)
    for key, given in (("flame_path", flame_path), ("mano_path", mano_path)):
        _template_file(cfg, key, given, dynamic, str(target.method))
    read = {plan[name].artifact.id: _manifest(plan[name]).output_digest for name in READS}
    return TrainedRun(subject_dir, str(target.method), cfg, read)


def _manifest(found: RecordedArtifact) -> Manifest:
    """The manifest of an artifact :func:`recorded_plan` found current (which has one)."""
    assert found.manifest is not None
    return found.manifest


def _workspace(subject_dir: Path, method: str, seed: int) -> tuple[Workspace, Artifact]:
    """(the subject's artifact tree, the run's trained model); :class:`ExportError` for a folder that is not there,
    a method or seed no run can have, and a subject without the run."""
    if not subject_dir.is_dir():
        raise ExportError(f"{subject_dir}: no such folder; give a subject's outputs folder (<paths.outputs>/<subject>)")
    problem = folder_name_problem(method)
    if problem is not None:
        raise ExportError(f"--method {method}: {problem}; give the name of a trained method, e.g. interactavatar")
    if seed_problem(seed) is not None:
        raise ExportError(f"--seed {seed}: use a non-negative integer, the training run's seed (0: the default run)")
    try:
        ws = Workspace(subject_dir.parent, subject_dir.name)
    except ValueError as exc:
        raise ExportError(f"{subject_dir}: not a subject's outputs folder ({exc})") from exc
    target = Artifact(MODEL_STAGE, method_run(method, seed))
    if not (ws.artifact_dir(target) / MANIFEST_NAME).is_file():
        raise ExportError(_no_model(subject_dir, method, seed, str(target.method)))
    return ws, target


def _computed_from(registry: StageRegistry, target: Artifact) -> list[Artifact]:
    """The artifacts ``target`` is computed from."""
    return [
        Artifact(s.name, target.method if s.per_method else None)
        for s in registry
        if s.name in registry.ancestors(target.stage)
    ]


def _train_command(subject_dir: Path, run: str, *settings: str) -> str:
    """The ``interactavatar`` command that computes the trained model of ``run`` for the subject in ``subject_dir``
    (with ``settings``: overrides such as ``fit.source=fitted``)."""
    where = (f"paths.outputs={subject_dir.parent}", f"subject={subject_dir.name}")
    return fix_command(OmegaConf.create({}), *where, *run_overrides(run), *settings, f"run.until={MODEL_STAGE}")


def _no_model(subject_dir: Path, method: str, seed: int, run: str) -> str:
    """The line for a subject folder without the trained run ``run``: the runs trained there, and the command that
    trains it where the pipeline has the method."""
    trained = sorted(p.parent.parent.name for p in subject_dir.glob(f"{METHODS_DIR}/*/{MODEL_STAGE}/{MANIFEST_NAME}"))
    nested = sorted(p.parent.name for p in subject_dir.glob(f"*/{METHODS_DIR}"))
    if nested and not trained:
        return f"{subject_dir}: not a subject's outputs folder; give one, e.g. {subject_dir / nested[0]}"
    there = f"; trained here: {', '.join(trained)} (--method, --seed)" if trained else ""
    methods = group_options("method")
    if method not in methods:
        return f"--method {method}: no such method; choose one of {', '.join(methods)}{there}"
    model_dir = subject_dir / METHODS_DIR / run / MODEL_STAGE
    return (
        f"{subject_dir}: no trained model of method '{method}' seed {seed} ({model_dir} has no {MANIFEST_NAME})"
        f"{there}; train it first: {_train_command(subject_dir, run)} (with the overrides the subject was run with)"
    )


def _stale_run(
    subject_dir: Path, target: Artifact, stale: list[RecordedArtifact], plan: dict[str, RecordedArtifact]
) -> str:
    """The line for a run the pipeline would compute again: what it would compute and why, and the command that does
    it, keeping the settings of what stays."""
    command = _train_command(subject_dir, str(target.method), *_settings_kept(stale, plan))
    return (
        f"{subject_dir}: the pipeline would compute {', '.join(r.artifact.id for r in stale)} again "
        f"({stale[0].artifact.id}: {stale[0].stale}): the model of {target.method} does not match what it would be "
        f"posed with; train it again, then export: {command} (with the overrides the subject was run with)"
    )


def _settings_kept(stale: list[RecordedArtifact], plan: dict[str, RecordedArtifact]) -> list[str]:
    """``key=value`` for each setting a stale artifact recorded with another value than an artifact that stays does
    (a fit republished with another ``fit.source``): the value that stays, so that the command keeps what stays."""
    kept = [_config(r.manifest) for r in plan.values() if r.stale is None and r.manifest is not None]
    overrides: dict[str, str] = {}
    for old in (_config(r.manifest) for r in stale if r.manifest is not None):
        for new in kept:
            for key in changed_keys(_plain(old), _plain(new)):
                before, now = (OmegaConf.select(c, key, default=_ABSENT) for c in (old, new))
                if before is not _ABSENT and now is not _ABSENT:
                    overrides.setdefault(key, f"{key}={'null' if now is None else now}")
    return list(overrides.values())


def _config(manifest: Manifest) -> DictConfig:
    """A manifest's settings (dotted keys) as one config."""
    cfg = OmegaConf.create({})
    for key, value in manifest.config.items():
        OmegaConf.update(cfg, key, value, merge=True)
    return cfg


def _plain(cfg: DictConfig) -> dict[str, Any]:
    plain = OmegaConf.to_container(cfg)
    assert isinstance(plain, dict)
    return {str(k): v for k, v in plain.items()}


def _settings(pbd: Manifest, dynamic: Manifest, placement: str) -> DictConfig:
    """The settings the run's stages ran with (the model's files, ``method.pbd``, the pbd solver's), from the pbd and
    dynamic stages' manifests, and ``reenact.placement``."""
    if placement not in PLACEMENTS:
        raise ExportError(f"--placement {placement}: choose one of {', '.join(PLACEMENTS)}")
    cfg = OmegaConf.merge(_config(pbd), _config(dynamic))
    assert isinstance(cfg, DictConfig)
    if OmegaConf.select(cfg, "method.pbd") is None:
        raise ExportError(f"the {MODEL_STAGE} stage's {MANIFEST_NAME} records no method.pbd; run the stage again")
    OmegaConf.update(cfg, "reenact.placement", placement)
    return cfg


def _template_file(cfg: DictConfig, key: str, given: str | None, dynamic: Manifest, run: str) -> None:
    """Set ``model.<key>`` in ``cfg`` to ``given`` (``--flame-path``, ``--mano-path``) where the run was posed with an
    official file, and check that the file it names is the one the run was posed with (the content digest the dynamic
    stage's manifest records)."""
    option, name = f"--{key.replace('_', '-')}", TEMPLATES[key]
    recorded = OmegaConf.select(cfg, f"model.{key}")
    if given is not None:
        if not recorded:
            raise ExportError(
                f"{option} {given}: the run {run} was posed with the built-in procedural {name} template, not an "
                f"official file; leave {option} out"
            )
        if not Path(given).is_file():
            raise ExportError(f"{option} {given}: no such file")
        OmegaConf.update(cfg, f"model.{key}", given)
    elif recorded and not Path(str(recorded)).is_file():
        raise ExportError(
            f"model.{key}={recorded}: no such file; the run {run} was posed with it: pass {option} with where it is now"
        )
    path = OmegaConf.select(cfg, f"model.{key}")
    if path and dynamic.sources and sha256_file(Path(str(path))) not in dynamic.sources.values():
        said = f"{option} {path}" if given is not None else f"model.{key}={path}"
        raise ExportError(
            f"{said}: not the {name} file the run {run} was posed with (its content differs from what the run "
            f"recorded); give {option} that file"
        )
