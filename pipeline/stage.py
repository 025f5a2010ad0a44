"""The stage contract: what a stage declares, and what it is handed when it runs.

A stage is a plain function wrapped in a :class:`Stage` that declares

- ``name``: unique within a registry, also the name of its output directory;
- ``inputs``: the upstream stages whose artifacts it reads (this defines the DAG);
- ``config_keys``: dotted paths into the resolved config that its output depends
  on (``"quality.image_size"``, ``"stage.capture"``); only these enter its cache key;
- ``cache_exclude``: dotted paths below ``config_keys`` that a stage reads but that
  cannot change what it writes (``"stage.warmup.checkpoint_every"``): left out of the key;
- ``unused_keys``: a function of the resolved config naming the paths at or below ``config_keys`` that this
  configuration does not read (another representation's recipe, the options of a solver not chosen): left out
  of the key too, so changing them reruns nothing (:func:`pipeline.config.key_config`);
- ``extra_keys``: a function of the resolved config naming further paths this configuration reads, which no fixed
  list can name (the method's representation's own section, whatever representation it is): they enter the key as
  ``config_keys`` do, and the config check requires them to be set;
- ``checks``: a function of the resolved config listing what this stage cannot run with (one line each, naming
  the key and the fix), beyond its schema's types and ranges; run with the rest of the check before any stage runs
  (the method's representation, e.g.);
- ``sources``: for stages that import user files (a capture folder), a function
  listing them; their content digests enter the cache key (``pipeline.sources``);
- ``reads_manifests``: the stage shows its inputs' run records (timings, metrics), so
  their whole manifests enter its key, not only their outputs (the report);
- ``outputs``: relative paths (files or directories) it must produce;
- ``version``: bumped by hand whenever the code changes what the stage writes;
- ``device``: the stage computes on ``run.device`` (it trains or renders); on any device but the CPU the device's
  kind enters its key, and its manifest records the device (:mod:`pipeline.device`);
- ``precision``: the stage runs the networks whose products ``run.precision`` sets (a ``device`` stage); other than
  fp32, the precision enters its key;
- ``config_schema``: optional dataclass that ``cfg.stage.<name>`` must match
  (checked, with types, before any stage runs);
- ``per_method``: the output depends on the method (``method=...``), so the runner keeps one artifact
  per method (``methods/<method>/<name>/``); its per-method inputs are the same method's. Every stage
  that reads a per-method stage is per-method itself, except through ``cross_method_inputs``;
- ``cross_method_inputs``, ``methods_key``: per-method stages whose artifacts of *several* methods the
  stage reads (the comparison): those of every method named by the config list at ``methods_key`` that
  has a complete artifact; their digests enter the key, so a method evaluated later reruns the stage;
  with ``seeds_key`` (a config list of seeds) every seed's run of each method (``method_run``), else seed 0's;
- ``subject_inputs``, ``input_subject``: shared stages of *another subject* of the same outputs folder
  that the stage reads (a reenactment's driver ``fit``) when ``input_subject(cfg)`` names one (``None``:
  none this time); their digests enter the key like any input's, so re-fitting the driver reruns it.

Stages never import each other: they talk only through artifacts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from omegaconf import DictConfig
from tqdm import tqdm

from data_schemas.sources import SourceLister

T = TypeVar("T")


@dataclass
class StageContext:
    """Everything a running stage may touch.

    Attributes:
        cfg: the whole resolved config (read-only by convention; a stage must read
            only keys under its declared ``config_keys``).
        subject: subject id, e.g. ``"synth_a"``.
        out_dir: a fresh temporary directory; the stage writes its outputs here and
            the runner moves it into place when the stage returns.
        inputs: upstream stage name -> its completed artifact directory.
        scratch_dir: persistent space for checkpoints: it survives a killed run and is
            handed to the next run with the same cache key (so it can resume), and is
            removed once the stage is published.
        metrics: scalar results the stage wants recorded in its manifest and
            shown in the final table (e.g. ``{"frames": 12}``).
        show_progress: whether progress bars are drawn.
        method_problems: for the cross-method inputs, run folder -> why an artifact that is on disk could not
            be used (``"dynamic: file ... does not match its manifest"``); such runs are absent from
            ``method_inputs``.
        device: the torch device a ``device`` stage computes on (``cpu``, ``cuda:N``; :mod:`pipeline.device`).
        precision: ``fp32``, or ``bf16`` for the MLPs' products.
    """

    cfg: DictConfig
    subject: str
    out_dir: Path
    inputs: Mapping[str, Path]
    scratch_dir: Path | None = None
    metrics: dict[str, float | int | str] = field(default_factory=dict)
    show_progress: bool = True
    method: str | None = None
    method_inputs: Mapping[str, Mapping[str, Path]] = field(default_factory=dict)
    subject_inputs: Mapping[str, Path] = field(default_factory=dict)
    method_problems: Mapping[str, str] = field(default_factory=dict)
    device: str = "cpu"
    precision: str = "fp32"

    def input_dir(self, stage: str) -> Path:
        """Artifact directory of a declared upstream stage (of this run's method where it is per-method)."""
        try:
            return self.inputs[stage]
        except KeyError as exc:
            raise KeyError(f"stage reads '{stage}' but does not declare it in inputs={sorted(self.inputs)}") from exc

    def subject_input_dir(self, stage: str) -> Path:
        """Artifact directory of a declared ``subject_inputs`` stage of the other subject ``input_subject`` names."""
        try:
            return self.subject_inputs[stage]
        except KeyError as exc:
            raise KeyError(
                f"stage reads '{stage}' of another subject, but input_subject names none for this "
                f"config or the stage does not declare it in subject_inputs"
            ) from exc

    def method_dirs(self, stage: str) -> Mapping[str, Path]:
        """method name -> complete artifact directory of ``stage``, for a declared cross-method input."""
        try:
            return self.method_inputs[stage]
        except KeyError as exc:
            raise KeyError(
                f"stage reads '{stage}' of several methods but does not declare it in "
                f"cross_method_inputs={sorted(self.method_inputs)}"
            ) from exc

    def progress(self, items: Iterable[T], desc: str, total: int | None = None) -> Iterator[T]:
        """Wrap a long loop in a progress bar (a no-op when progress is off)."""
        return iter(tqdm(items, desc=desc, total=total, disable=not self.show_progress, leave=False))


StageFn = Callable[[StageContext], None]
SubjectChooser = Callable[[DictConfig], "str | None"]


@dataclass(frozen=True)
class Stage:
    """A declared node of the DAG. See the module docstring for the fields."""

    name: str
    fn: StageFn
    inputs: tuple[str, ...] = ()
    config_keys: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    version: str = "1"
    device: bool = False
    precision: bool = False
    config_schema: type | None = None
    description: str = ""
    cache_exclude: tuple[str, ...] = ()
    unused_keys: Callable[[DictConfig], Iterable[str]] | None = None
    extra_keys: Callable[[DictConfig], Iterable[str]] | None = None
    checks: Callable[[DictConfig], Iterable[str]] | None = None
    sources: SourceLister | None = None
    reads_manifests: bool = False
    per_method: bool = False
    cross_method_inputs: tuple[str, ...] = ()
    methods_key: str | None = None
    seeds_key: str | None = None
    subject_inputs: tuple[str, ...] = ()
    input_subject: SubjectChooser | None = None

    @property
    def reads(self) -> tuple[str, ...]:
        """Every stage this one reads (``inputs``, ``cross_method_inputs``, ``subject_inputs``): its DAG edges."""
        extra = (*self.cross_method_inputs, *self.subject_inputs)
        return self.inputs + tuple(dict.fromkeys(n for n in extra if n not in self.inputs))

    def keys(self, cfg: DictConfig) -> tuple[str, ...]:
        """The config paths this stage reads under ``cfg``: its ``config_keys`` and what ``extra_keys(cfg)`` adds."""
        extra = tuple(self.extra_keys(cfg)) if self.extra_keys is not None else ()
        return tuple(dict.fromkeys(self.config_keys + extra))

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("_", "").isalnum():
            raise ValueError(f"stage name must be alphanumeric/underscore, got {self.name!r}")
        if not self.outputs:
            raise ValueError(f"stage '{self.name}' declares no outputs")
        if self.name in self.reads:
            raise ValueError(f"stage '{self.name}' lists itself as an input")
        if bool(self.cross_method_inputs) != (self.methods_key is not None):
            raise ValueError(f"stage '{self.name}': cross_method_inputs and methods_key go together")
        if self.precision and not self.device:
            raise ValueError(f"stage '{self.name}': precision=True needs device=True (networks run on the device)")
        if self.seeds_key is not None and self.methods_key is None:
            raise ValueError(f"stage '{self.name}': seeds_key needs methods_key")
        if bool(self.subject_inputs) != (self.input_subject is not None):
            raise ValueError(f"stage '{self.name}': subject_inputs and input_subject go together")
        for key in self.cache_exclude:
            if not any(key.startswith(f"{k}.") for k in self.config_keys):
                raise ValueError(
                    f"stage '{self.name}': cache_exclude key '{key}' is not below one of its "
                    f"config_keys {self.config_keys}"
                )


def stage(
    name: str,
    *,
    inputs: Iterable[str] = (),
    config_keys: Iterable[str] = (),
    outputs: Iterable[str],
    version: str = "1",
    device: bool = False,
    precision: bool = False,
    config_schema: type | None = None,
    cache_exclude: Iterable[str] = (),
    unused_keys: Callable[[DictConfig], Iterable[str]] | None = None,
    extra_keys: Callable[[DictConfig], Iterable[str]] | None = None,
    checks: Callable[[DictConfig], Iterable[str]] | None = None,
    sources: SourceLister | None = None,
    reads_manifests: bool = False,
    per_method: bool = False,
    cross_method_inputs: Iterable[str] = (),
    methods_key: str | None = None,
    seeds_key: str | None = None,
    subject_inputs: Iterable[str] = (),
    input_subject: SubjectChooser | None = None,
) -> Callable[[StageFn], Stage]:
    """Decorator that turns ``fn(ctx)`` into a :class:`Stage`; the docstring becomes its description."""

    def wrap(fn: StageFn) -> Stage:
        return Stage(
            name=name,
            fn=fn,
            inputs=tuple(inputs),
            config_keys=tuple(config_keys),
            outputs=tuple(outputs),
            version=version,
            device=device,
            precision=precision,
            config_schema=config_schema,
            cache_exclude=tuple(cache_exclude),
            unused_keys=unused_keys,
            extra_keys=extra_keys,
            checks=checks,
            sources=sources,
            reads_manifests=reads_manifests,
            per_method=per_method,
            cross_method_inputs=tuple(cross_method_inputs),
            methods_key=methods_key,
            seeds_key=seeds_key,
            subject_inputs=tuple(subject_inputs),
            input_subject=input_subject,
            description=(fn.__doc__ or "").strip().splitlines()[0] if fn.__doc__ else "",
        )

    return wrap
