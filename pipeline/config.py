"""Typed schemas for the runner's own config, and validation of a whole config before any stage runs.

Every problem found is collected into one :class:`ConfigError`, so a user sees
all of them at once, before anything is written.
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra._internal.config_repository import ConfigRepository
from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from data_schemas.config_sections import check_section
from importers.decaf import ships_keypoints
from pipeline.device import device_syntax_problem, precision_problem
from pipeline.overrides import added_key_problems
from pipeline.registry import RegistryError, StageRegistry
from pipeline.stage import Stage
from pipeline.threads import threads_problem
from pipeline.workspace import method_problem, outputs_problem, seed_problem, subject_problem

#: the app's config tree (Hydra's ``config_path``): ``config.yaml`` and one folder per config group
CONF_DIR = Path(__file__).resolve().parent.parent / "conf"


def decaf_detector(root: str | None, subject: str) -> str:
    """``stage.keypoints.detector``'s default for ``dataset=decaf`` (the resolver ``decaf_detector``):
    ``provided`` where the release ships keypoint files for ``subject``, else ``mediapipe``."""
    return "provided" if root and ships_keypoints(root, subject) else "mediapipe"


OmegaConf.register_new_resolver("decaf_detector", decaf_detector, replace=True)


class ConfigError(ValueError):
    """The config cannot run; the message lists every problem and how to fix it, ``problems`` each of them."""

    def __init__(self, message: str, problems: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.problems = tuple(problems) or (message,)


def group_options(group: str) -> list[str]:
    """The options of the config group ``group``, e.g. the methods: ``conf/<group>/<option>.yaml`` and, inside a
    Hydra run, those of the folders and packages on its ``hydra.searchpath`` (a method defined by one YAML file
    of the user's)."""
    Plugins.instance()  # registers Hydra's config sources (file://, pkg://) where no Hydra app has yet
    search_path = ConfigSearchPathImpl()
    search_path.append("main", f"file://{CONF_DIR}")
    for extra in HydraConfig.get().searchpath if HydraConfig.initialized() else ():
        search_path.append("searchpath", str(extra))
    return sorted(ConfigRepository(config_search_path=search_path).get_group_options(group))


@dataclass
class RunConfig:
    """``run.*``: which stages to consider and how."""

    only: str | None = None  # run just this stage (its inputs must already be complete)
    # ``from`` is a Python keyword; the YAML key is ``from`` and maps onto this field by name.
    until: str | None = None  # this stage and everything it depends on
    force: bool = False  # recompute selected stages even when cached
    dry: bool = False  # print the plan and the reason per stage, run nothing
    progress: bool = True  # progress bars for long loops
    lock_timeout_s: float = 3600.0  # how long to wait for another run holding a stage lock
    device: str = "auto"  # where the stages that train and render compute: auto, cpu, cuda, cuda:N (pipeline.device)
    precision: str = "fp32"  # fp32, or bf16: the networks' products in bfloat16 (H, I, PointNet++)
    threads: str = "auto"  # CPU threads of a job: auto (the cores it may use, shared by a local batch's jobs) or N
    overrides: list[str] = field(default_factory=list)  # set by the CLI: the command line's overrides


#: overrides a fix command sets itself, or that select what to run rather than what is computed
_NOT_REPEATED = ("run.", "+run.", "method=", "method.", "+method.", "seed=", "hydra.", "hydra/", "~")
#: the ``run.*`` overrides that decide what is computed (where, in which precision): a fix command repeats them
_REPEATED_RUN = ("run.device=", "+run.device=", "run.precision=", "+run.precision=")


def fix_command(cfg: DictConfig, *args: str) -> str:
    """A shell command for a message that tells the user how to fix something: ``interactavatar``, this run's
    own command-line overrides (``run.overrides``; those that decide where and from what the stages compute:
    ``paths.outputs``, ``subject``, ``quality``, ``fit.source``, ``run.device``, ``run.precision``, ...; not the
    other ``run.*``, ``method``, ``seed``) and ``args``, which win over an override of the same key. Run as printed,
    it computes in the same DAG."""
    own = {arg.split("=", 1)[0].lstrip("+") for arg in args}
    kept = [
        o
        for o in (OmegaConf.select(cfg, "run.overrides") or ())
        if (str(o).startswith(_REPEATED_RUN) or not str(o).startswith(_NOT_REPEATED))
        and str(o).split("=", 1)[0].lstrip("+") not in own
    ]
    return " ".join(["interactavatar", *(shlex.quote(str(o)) for o in kept), *(shlex.quote(a) for a in args)])


@dataclass
class PathsConfig:
    outputs: str = "outputs"


@dataclass
class QualityConfig:
    """``quality.*``: the preset's speed/fidelity knobs (values in ``conf/quality/<name>.yaml``)."""

    name: str
    capture_size: int  # synthetic capture: render resolution per camera (px)
    image_size: int  # crops fed to the avatar (px)
    num_frames_train: int
    num_frames_test: int
    supersample: int  # antialiasing samples per pixel side
    gaussians_per_triangle: int
    warmup_steps: int
    dynamic_steps: int  # stage two (stage dynamic)
    dynamic_width: int  # units per MLP layer
    dynamic_hand_depth: int
    dynamic_interaction_depth: int
    geometry_feature_dim: int  # PointNet++ feature F
    pointnet_width: float  # multiplier of the PointNet++ layer widths
    pointnet_centres: list[int]  # set-abstraction centres of the two levels

    @classmethod
    def validate(cls, conf: Any) -> list[str]:
        """Range problems, one line each, keyed relative to ``quality``."""
        limits = {
            "capture_size": (16, 8192),
            "image_size": (16, 8192),
            "num_frames_train": (1, None),
            "num_frames_test": (1, None),
            "supersample": (1, 8),
            "gaussians_per_triangle": (1, 1000),
            "warmup_steps": (1, None),
            "dynamic_steps": (0, None),
            "dynamic_width": (1, 4096),
            "dynamic_hand_depth": (1, 32),
            "dynamic_interaction_depth": (1, 32),
            "geometry_feature_dim": (1, 8192),
            "pointnet_width": (0.01, 16),
        }
        problems = [
            problem
            for key, (low, high) in limits.items()
            if (problem := _range_problem(key, getattr(conf, key), low, high))
        ]
        if len(conf.pointnet_centres) != 2 or min(conf.pointnet_centres) < 1:
            problems.append(
                f"pointnet_centres={list(conf.pointnet_centres)}: must be two positive counts "
                f"(centres of the two set-abstraction levels)"
            )
        return problems


def _range_problem(key: str, value: float, low: float, high: float | None) -> str | None:
    """``key=value: must be ...`` when ``value`` lies outside ``[low, high]`` (``high=None``: unbounded)."""
    if value >= low and (high is None or value <= high):
        return None
    bound = f"at least {low}" if high is None else f"between {low} and {high}"
    return f"{key}={value}: must be {bound}"


def validate_config(cfg: DictConfig, registry: StageRegistry) -> DictConfig:
    """``cfg`` with every stage section completed by its schema's defaults.

    Raises :class:`ConfigError` listing every problem in ``cfg`` for this ``registry``.
    """
    cfg = cfg.copy()
    errors: list[str] = []
    run = cfg.get("run")
    if run is None:
        errors.append("missing section 'run'")
    else:
        run_values = OmegaConf.to_container(run, resolve=True)
        if not isinstance(run_values, dict):
            raise ConfigError(f"run: must be a mapping of run.* settings, got {run_values!r}")
        run_plain = {k: v for k, v in run_values.items() if k != "from"}
        check_section(run_plain, RunConfig, "run", errors)
        known = registry.names()
        for key in ("only", "from", "until"):
            name = run.get(key)
            if name is not None and name not in registry:
                errors.append(f"run.{key}={name}: unknown stage; choose one of {', '.join(known)}")
        if run.get("only") is not None and (run.get("from") is not None or run.get("until") is not None):
            errors.append("run.only cannot be combined with run.from or run.until")
        errors.extend(
            p
            for p in (
                device_syntax_problem(run.get("device", "auto")),
                precision_problem(run.get("precision", "fp32")),
                threads_problem(run.get("threads", "auto")),
            )
            if p is not None
        )
    paths = check_section(cfg.get("paths", {}), PathsConfig, "paths", errors)
    if paths is not None and (problem := outputs_problem(paths.outputs)):
        errors.append(problem)
    if cfg.get("quality") is None:
        errors.append("missing section 'quality'; choose a preset, e.g. quality=smoke")
    else:
        check_section(cfg.quality, QualityConfig, "quality", errors)
    problem = subject_problem(cfg.get("subject"))
    if problem:
        errors.append(problem)
    if cfg.get("dataset") is not None:
        errors.extend(dataset_problems(cfg))

    try:
        stages = registry.topological()
    except RegistryError as exc:
        errors.append(str(exc))
        stages = []
    if any(s.per_method for s in stages):
        problem = method_problem(OmegaConf.select(cfg, "method.name", default=None))
        if problem:
            errors.append(
                f"{problem} (stages {', '.join(s.name for s in stages if s.per_method)} keep one artifact per method)"
            )
        problem = seed_problem(OmegaConf.select(cfg, "seed", default=0))
        if problem:
            errors.append(f"{problem} (the training run's seed: stage.warmup.seed and stage.dynamic.seed follow it)")
    for s in stages:
        for list_key, what, problem_of in (
            (s.methods_key, "method names", method_problem),
            (s.seeds_key, "seeds, e.g. [0, 1, 2]", seed_problem),
        ):
            if list_key is None:
                continue
            values = OmegaConf.select(cfg, list_key, default=None)
            if not OmegaConf.is_list(values) or not values:
                errors.append(f"{list_key}: stage '{s.name}' needs a non-empty list of {what}")
            else:
                errors.extend(p for value in values if (p := problem_of(value, list_key)))
        for key in s.keys(cfg):
            if OmegaConf.select(cfg, key, default=_MISSING) is _MISSING:
                errors.append(f"stage '{s.name}' depends on config key '{key}', which is not set")
        if s.config_schema is not None:
            section = OmegaConf.select(cfg, f"stage.{s.name}", default=None)
            if section is None:
                errors.append(f"stage.{s.name}: missing (expected fields of {s.config_schema.__name__})")
            else:
                typed = check_section(section, s.config_schema, f"stage.{s.name}", errors)
                if typed is not None:
                    with open_dict(cfg):
                        cfg.stage[s.name] = typed
    errors.extend(added_key_problems(cfg, errors))
    if not errors:  # the stages' own checks read sections the schemas have typed
        errors.extend(dict.fromkeys(p for s in stages if s.checks is not None for p in s.checks(cfg)))
    errors.extend(numeric_problems(cfg, errors))
    if errors:  # one problem on one line, several one per line
        listed = f" {errors[0]}" if len(errors) == 1 else "\n  - " + "\n  - ".join(errors)
        raise ConfigError(f"invalid config:{listed}", errors)
    return cfg


#: Root sections the numeric check leaves out: Hydra's own settings.
NOT_SETTINGS = ("hydra",)


def numeric_problems(cfg: DictConfig, known: list[str]) -> list[str]:
    """Every number of the resolved config, in every section (stages, presets, dataset, reenact, ...): finite
    and not negative, the ranges of every setting the app has (no shipped value is negative; the counts, sizes,
    weights, rates, radii, thresholds and times are not). Keys a more specific check already named in
    ``known`` are left to that message. One line per key."""
    plain = {k: v for k, v in cfg.items() if k not in NOT_SETTINGS}
    try:
        values = OmegaConf.to_container(OmegaConf.create(plain), resolve=True)
    except OmegaConfBaseException:
        return []  # an interpolation that does not resolve: reported where the section is checked
    problems = []
    for key, value in _numbers(values, ""):
        if any(f"{key}=" in line or line.startswith(f"{key}:") for line in known):
            continue
        if not math.isfinite(value):
            problems.append(f"{key}={value}: must be a finite number")
        elif value < 0:
            problems.append(f"{key}={value}: must not be negative")
    return problems


def _numbers(node: Any, prefix: str) -> list[tuple[str, float]]:
    """(dotted key, value) of every int and float leaf below ``node`` (bools are not numbers here)."""
    if isinstance(node, dict):
        return [item for k, v in node.items() for item in _numbers(v, f"{prefix}{k}.")]
    if isinstance(node, list):
        return [item for i, v in enumerate(node) for item in _numbers(v, f"{prefix[:-1]}[{i}].")]
    if isinstance(node, (int, float)) and not isinstance(node, bool):
        return [(prefix[:-1], float(node))]
    return []


_MISSING = object()
SYNTHETIC_CAMERA_IDS = "cam{:02d}"  # the synthetic rig's camera ids, cam00 .. (avatar/synthetic/rig.py)


def _int_problem(key: str, value: object, minimum: int) -> str | None:
    if isinstance(value, bool) or not isinstance(value, int):
        return f"{key}={value!r}: must be a whole number >= {minimum}"
    return f"{key}={value}: must be >= {minimum}" if value < minimum else None


#: what a dataset on disk reads below ``dataset.root`` (conf/dataset/<name>.yaml)
DATASET_LAYOUTS = {"folder": "<root>/<subject>/...", "decaf": "<root>/{train,test}/.../<subject>/..."}


def synthetic_camera_ids(cfg: DictConfig) -> list[str]:
    """The synthetic rig's camera ids under ``cfg``: ``cam00`` .. for ``stage.capture.num_cameras`` cameras."""
    count = int(OmegaConf.select(cfg, "stage.capture.num_cameras", default=0) or 0)
    return [SYNTHETIC_CAMERA_IDS.format(i) for i in range(count)]


def dataset_problems(cfg: DictConfig) -> list[str]:
    """Problems of the ``dataset`` section, one line each, before any stage runs: ``root`` set where the dataset
    reads one; ``start_frame`` (>= 0), ``frame_step`` (>= 1) and ``max_frames`` (null or >= 1) whole numbers;
    ``train_cameras`` null or a non-empty list of camera ids, and, for the synthetic rig whose ids are known
    now (:func:`synthetic_camera_ids`), some but not all of them."""
    dataset = cfg.dataset
    name = dataset.get("name")
    problems: list[str | None] = []
    if OmegaConf.is_missing(dataset, "root"):
        problems.append(
            f"dataset.root: not set; dataset={name} reads {DATASET_LAYOUTS.get(str(name), '<root>/...')}; "
            f"set dataset.root=/path"
        )
    for key, minimum in (("start_frame", 0), ("frame_step", 1), ("max_frames", 1)):
        if key in dataset and not (key == "max_frames" and dataset[key] is None):
            problems.append(_int_problem(f"dataset.{key}", dataset[key], minimum))
    train = dataset.get("train_cameras")
    if train is not None:
        if (
            not OmegaConf.is_list(train)
            or not train
            or not all(isinstance(c, (str, int)) and not isinstance(c, bool) for c in train)
        ):
            problems.append(f"dataset.train_cameras={train}: a non-empty list of camera ids, e.g. [cam04], or null")
        elif name == "synthetic":
            ids = synthetic_camera_ids(cfg)
            if not {str(c) for c in train} < set(ids):
                problems.append(
                    f"dataset.train_cameras={list(train)}: choose some but not all of the synthetic rig's cameras {ids}"
                )
    return [p for p in problems if p]


def key_config(cfg: DictConfig, s: Stage) -> dict[str, Any]:
    """The settings that enter stage ``s``'s cache key under ``cfg``: the resolved values of its ``config_keys`` and
    ``extra_keys(cfg)`` without its ``cache_exclude`` and without what its ``unused_keys(cfg)`` names."""
    keys = s.keys(cfg)
    unused = tuple(s.unused_keys(cfg)) if s.unused_keys is not None else ()
    for key in unused:
        if not any(key == k or key.startswith(f"{k}.") for k in keys):
            raise ValueError(f"stage '{s.name}': unused key '{key}' is not one of its config_keys {keys} or below one")
    return config_subset(cfg, tuple(k for k in keys if k not in unused), s.cache_exclude + unused)


def config_subset(cfg: DictConfig, keys: tuple[str, ...], exclude: tuple[str, ...] = ()) -> dict[str, Any]:
    """The resolved values of the dotted ``keys``, as plain JSON-able data, without the dotted ``exclude``
    paths below them (settings that cannot change a stage's result, e.g. its checkpoint interval)."""
    out: dict[str, Any] = {}
    for key in keys:
        value = OmegaConf.select(cfg, key, throw_on_missing=True)
        out[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    for path in exclude:
        owner = next((k for k in keys if path.startswith(f"{k}.")), None)
        if owner is None:  # the whole key is left out (or is not among keys)
            continue
        *parents, leaf = path[len(owner) + 1 :].split(".")
        node = out[owner]
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(leaf, None)
    return out


def changed_keys(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Dotted leaf keys whose values differ between two config subsets."""
    flat_old, flat_new = _flatten(old), _flatten(new)
    return sorted(k for k in set(flat_old) | set(flat_new) if flat_old.get(k, _MISSING) != flat_new.get(k, _MISSING))


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: d}
