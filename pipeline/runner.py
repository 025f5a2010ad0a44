"""Plan and execute a DAG of stages for one subject, with content-addressed caching.

For each stage the runner decides, and prints with its reason, one of:

- ``cached``: the manifest's key matches and every output hashes as recorded;
- ``run``: forced, never run, config/code/upstream changed, or outputs missing or corrupted;
- ``skip``: not selected by ``run.only`` / ``run.from`` / ``run.until``.

A stage is first decided under read locks on it and its inputs: a cached one is done
then, so it never waits for other runs that only read it (methods of one subject run
side by side and read the shared stages for hours). Execution holds the stage's write
lock and read locks on its inputs, re-decides under them (another run may just have
produced the stage or replaced an input),
writes into a temporary directory, checks that the inputs it read are still the
ones its manifest names, and publishes atomically with the manifest written last.
"""

from __future__ import annotations

import datetime as dt
import errno
import functools
import shutil
import subprocess
from collections.abc import Callable, Collection
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from data_schemas.tables import SchemaError
from pipeline.config import ConfigError, changed_keys, fix_command, key_config
from pipeline.device import DeviceUnavailable, resolve_compute
from pipeline.manifest import (
    Manifest,
    ManifestError,
    cache_key,
    hash_outputs,
    read_manifest,
    verify_outputs,
    write_manifest,
)
from pipeline.monitor import ResourceMonitor
from pipeline.registry import StageRegistry
from pipeline.sources import changed_sources, hash_sources
from pipeline.stage import Stage, StageContext
from pipeline.threads import torch_threads
from pipeline.workspace import Artifact, LockTimeout, Workspace, method_run, run_overrides, subject_problem

Log = Callable[[str], None]


@dataclass(frozen=True)
class Selection:
    """Which stages a run considers (``run.only``/``from``/``until``) and whether to force them."""

    only: str | None = None
    start: str | None = None
    until: str | None = None
    force: bool = False

    @classmethod
    def from_cfg(cls, run: DictConfig) -> Selection:
        return cls(only=run.get("only"), start=run.get("from"), until=run.get("until"), force=bool(run.get("force")))

    def stages(self, registry: StageRegistry) -> list[str]:
        """Selected stage names in topological order."""
        names = registry.names()
        if self.only is not None:
            return [self.only]
        keep = set(names)
        if self.start is not None:
            keep &= {self.start} | registry.descendants(self.start)
        if self.until is not None:
            keep &= {self.until} | registry.ancestors(self.until)
        return [n for n in names if n in keep]


@dataclass
class StageReport:
    """What happened to one stage in this run."""

    stage: str
    action: str  # "run", "cached", "shared" (another method's identical artifact), "skip", "would run"
    reason: str
    wall_s: float = 0.0
    peak_rss_mb: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)


class StageFailed(RuntimeError):
    """A stage raised; nothing of it was published.

    With ``written`` (the folder it was computing into, removed now) and ``output`` (where its artifact lives), the
    message names the output wherever the cause named the removed folder, and says that nothing was written there.
    """

    def __init__(
        self, stage: str, cause: BaseException, fix: str | None = None, written: tuple[Path, Path] | None = None
    ) -> None:
        said = str(cause) if written is None else str(cause).replace(str(written[0]), str(written[1]))
        where = f"; nothing was written to {written[1]}" if written is not None else ""
        super().__init__(
            f"stage '{stage}' failed: {type(cause).__name__}: {said}" + (f"; {fix}" if fix else "") + where
        )
        self.stage = stage


class Interrupted(RuntimeError):
    """The user stopped the run (Ctrl-C, SIGINT) while a stage was computing: nothing of that stage was published,
    the stages finished before it are kept, and so is the stage's checkpoint when it had written one."""

    def __init__(self, stage: str, checkpoint: Path | None) -> None:
        kept = (
            f"its checkpoint in {checkpoint} is kept, and the same command resumes from it"
            if checkpoint is not None
            else "it had no checkpoint yet, so the same command starts it over"
        )
        super().__init__(
            f"interrupted during stage '{stage}': nothing of it was published (its previous artifact, if any, is "
            f"kept, as are the stages finished before it); {kept}"
        )
        self.stage = stage


class MissingUpstream(RuntimeError):
    """A selected stage reads a stage that has no complete artifact and is not selected."""


@dataclass
class _Decision:
    run: bool
    reason: str
    key: str
    config: dict[str, Any]
    upstream: dict[str, str]
    sources: dict[str, str] | None
    inputs: dict[str, Artifact]


class Runner:
    """Runs a registry's stages for one subject (and one method, for the per-method stages).

    Args:
        cfg: the whole resolved config (already validated).
        registry: the DAG.
        log: where one-line decisions and the summary go.
    """

    def __init__(self, cfg: DictConfig, registry: StageRegistry, log: Log = print) -> None:
        self.cfg = cfg
        self.registry = registry
        self.log = log
        self.ws = Workspace(Path(cfg.paths.outputs), cfg.subject)
        method = OmegaConf.select(cfg, "method.name", default=None)
        # the run's folder under methods/: the method's name, with its seed unless 0 (pipeline.workspace.method_run)
        self.method: str | None = (
            None if method is None else method_run(str(method), int(OmegaConf.select(cfg, "seed", default=0)))
        )
        self.selection = Selection.from_cfg(cfg.run)
        self.show_progress = bool(cfg.run.get("progress", True))
        self.lock_timeout_s = float(cfg.run.get("lock_timeout_s", 3600.0))
        try:  # on the machine that runs the stages, before any of them
            self.compute = resolve_compute(str(cfg.run.get("device", "auto")), str(cfg.run.get("precision", "fp32")))
        except DeviceUnavailable as exc:
            raise ConfigError(f"invalid config:\n  - {exc}", [str(exc)]) from exc
        # Artifacts (by id) this run has verified or written, so each is hashed once per run.
        self._verified: dict[str, Manifest] = {}

    # ----------------------------------------------------------------- artifacts
    def artifact(self, stage: str) -> Artifact:
        """This run's artifact of ``stage``: its method's own for a per-method stage, else the shared one."""
        return Artifact(stage, self.method if self.registry[stage].per_method else None)

    def artifact_dir(self, stage: str) -> Path:
        return self.ws.artifact_dir(self.artifact(stage))

    def _inputs(self, s: Stage, pending: set[str]) -> dict[str, Artifact]:
        """Upstream key -> artifact of everything ``s`` reads: its inputs under their stage names, and the
        cross-method inputs as ``stage@method`` for each configured method with a complete artifact (or
        one this run plans to write)."""
        out = {name: self.artifact(name) for name in s.inputs}
        for a in self._cross_method_artifacts(s):
            if a.key in pending or self._verified.get(a.key) or self._verify(a):
                out[a.key] = a
        other = s.input_subject(self.cfg) if s.input_subject is not None else None
        if other is not None and other == self.ws.subject:
            raise ConfigError(
                f"stage '{s.name}' reads another subject's artifacts, but the config names this run's "
                f"own subject '{other}' for them; name a different subject, or 'self' for this "
                f"subject's own data (e.g. reenact.driver=self)"
            )
        if other is not None:
            problem = subject_problem(other)
            if problem:
                raise ConfigError(f"stage '{s.name}' reads another subject: {problem}")
            out.update({a.key: a for a in (Artifact(name, None, other) for name in s.subject_inputs)})
        return out

    def _cross_method_artifacts(self, s: Stage) -> list[Artifact]:
        """Every cross-method artifact ``s`` may read: each of its cross-method stages for each configured
        method and seed, whether or not it is on disk."""
        methods = OmegaConf.select(self.cfg, s.methods_key) if s.methods_key else None
        seeds = OmegaConf.select(self.cfg, s.seeds_key) if s.seeds_key else None
        runs = [method_run(str(m), int(seed)) for m in methods or () for seed in seeds or (0,)]
        return [Artifact(name, run) for name in s.cross_method_inputs for run in runs]

    def _cross_method_problems(self, s: Stage, inputs: dict[str, Artifact]) -> dict[str, str]:
        """Run folder -> why its cross-method artifact of ``s`` is on disk but unusable (corrupt, unreadable)."""
        problems: dict[str, str] = {}
        for a in self._cross_method_artifacts(s):
            if a.key in inputs or not self.ws.artifact_dir(a).exists():
                continue
            problems.setdefault(str(a.method), f"{a.stage}: {self._integrity(a)[1]}")
        return problems

    def _context_inputs(
        self, s: Stage, inputs: dict[str, Artifact]
    ) -> tuple[dict[str, Path], dict[str, dict[str, Path]], dict[str, Path]]:
        """(stage -> dir of the regular inputs, stage -> method -> dir of the cross-method ones,
        stage -> dir of the other subject's)."""
        regular = {name: self.ws.artifact_dir(inputs[name]) for name in s.inputs}
        cross: dict[str, dict[str, Path]] = {name: {} for name in s.cross_method_inputs}
        other: dict[str, Path] = {}
        for key, a in inputs.items():
            if a.subject is not None:
                other[a.stage] = self.ws.artifact_dir(a)
            elif key not in regular:
                cross[a.stage][str(a.method)] = self.ws.artifact_dir(a)
        return regular, cross, other

    # ----------------------------------------------------------------- decisions
    def _upstream_digests(
        self, s: Stage, inputs: dict[str, Artifact], pending: set[str]
    ) -> tuple[dict[str, str], list[str]]:
        """Output digest of each input, and the inputs that are planned to rerun (dry runs only)."""
        digests: dict[str, str] = {}
        rerunning: list[str] = []
        for key, a in inputs.items():
            if a.key in pending:
                rerunning.append(key)
                continue
            manifest = self._verified.get(a.key) or self._verify(a)
            if manifest is None:
                up_dir = self.ws.artifact_dir(a)
                fix = fix_command(
                    self.cfg,
                    f"subject={a.subject or self.ws.subject}",
                    *(run_overrides(a.method) if a.method else ()),
                    f"run.until={a.stage}",
                )
                raise MissingUpstream(
                    f"stage '{s.name}' reads '{a.key}', which has no complete artifact in {up_dir}; "
                    f"run it first (e.g. {fix})"
                )
            digests[key] = _input_digest(s, manifest)
        return digests, rerunning

    def _readable_manifest(self, a: Artifact) -> Manifest | None:
        """The artifact's manifest as it is on disk now; ``None`` when missing or untrustworthy."""
        try:
            return read_manifest(self.ws.artifact_dir(a))
        except ManifestError:
            return None

    def _integrity(self, a: Artifact) -> tuple[Manifest | None, str | None]:
        """(the artifact's manifest, None) if it and every output on disk are whole, else (None, why not)."""
        manifest = self._readable_manifest(a)
        if manifest is None:
            return None, "no readable manifest"
        why = verify_outputs(self.ws.artifact_dir(a), manifest, self.registry[a.stage].outputs)
        return (None, why) if why is not None else (manifest, None)

    def _verify(self, a: Artifact) -> Manifest | None:
        """The artifact's manifest if it and every output on disk are whole (remembered for this run)."""
        manifest = self._integrity(a)[0]
        if manifest is not None:
            self._verified[a.key] = manifest
        return manifest

    def _forget_replaced_inputs(self, inputs: dict[str, Artifact]) -> None:
        """Drop remembered verifications of inputs that another run replaced since (call under the locks)."""
        for a in inputs.values():
            known = self._verified.get(a.key)
            if known is None:
                continue
            current = self._readable_manifest(a)
            if current is None or (current.key, current.output_digest) != (known.key, known.output_digest):
                del self._verified[a.key]

    def _source_digests(self, s: Stage) -> dict[str, str] | None:
        """Digests of the user files the stage imports, or ``None`` when it declares none."""
        if s.sources is None:
            return None
        try:
            files = s.sources(self.cfg, self.ws.subject)
        except SchemaError as exc:  # a setting names a file that is not there: a config error, before any work
            raise ConfigError(f"stage '{s.name}': {exc}") from exc
        return hash_sources(files, self.ws.root / ".cache" / "sources.json")

    def _check_inputs_unchanged(self, s: Stage, d: _Decision) -> None:
        """Raise if an input artifact or source file differs from what the decision recorded."""
        for key, digest in d.upstream.items():
            current = self._readable_manifest(d.inputs[key])
            if current is None or _input_digest(s, current) != digest:
                raise RuntimeError(
                    f"input '{key}' was replaced while the stage ran (by a run that did not hold "
                    f"its lock); nothing was published: rerun"
                )
        if d.sources is not None:
            changed = changed_sources(d.sources, self._source_digests(s) or {})
            if changed:
                raise RuntimeError(
                    f"source files changed while the stage ran ({', '.join(changed)}); nothing "
                    f"was published: rerun once they are complete"
                )

    def _decide(self, s: Stage, force: bool, pending: set[str]) -> _Decision:
        inputs = self._inputs(s, pending)
        upstream, rerunning = self._upstream_digests(s, inputs, pending)
        config = key_config(self.cfg, s)
        config["subject"] = self.ws.subject
        if s.device:  # nothing on the CPU in fp32: the reference's keys stay as they were
            config.update(self.compute.key_entries(s.precision))
        sources = self._source_digests(s)
        key = cache_key(s.name, s.version, config, upstream, sources)

        def decision(run: bool, reason: str) -> _Decision:
            return _Decision(run, reason, key, config, upstream, sources, inputs)

        if force:
            return decision(True, "forced")
        if rerunning:
            return decision(True, f"upstream reruns: {', '.join(rerunning)}")
        a = self.artifact(s.name)
        stage_dir = self.ws.artifact_dir(a)
        try:
            manifest = read_manifest(stage_dir)
        except ManifestError as exc:
            return decision(True, f"manifest corrupted: {exc}")
        if manifest is None:
            return decision(True, "outputs missing" + ("" if stage_dir.exists() else ": never run"))
        if manifest.key != key:
            return decision(True, _why_key_changed(manifest, s.version, config, upstream, sources))
        problem = verify_outputs(stage_dir, manifest, s.outputs)
        if problem is None:
            self._verified[a.key] = manifest
        return decision(problem is not None, problem or "cached")

    def _same_key_elsewhere(self, s: Stage, key: str) -> Artifact | None:
        """Another method's whole artifact of the per-method stage ``s`` with cache key ``key``: the same
        content (same stage, code, config subset and inputs), so it is shared instead of recomputed."""
        if not s.per_method:
            return None
        for other in self.ws.method_artifacts(s.name):
            if other.method == self.method:
                continue
            manifest = self._readable_manifest(other)
            if manifest is not None and manifest.key == key:
                return other
        return None

    # ----------------------------------------------------------------- running
    def plan(self) -> list[StageReport]:
        """Decide every stage without running anything (``run.dry=true``)."""
        selected = set(self.selection.stages(self.registry))
        pending: set[str] = set()
        reports = []
        for s in self.registry:
            if s.name not in selected:
                reports.append(StageReport(s.name, "skip", "not selected"))
                continue
            d = self._decide(s, self.selection.force, pending)
            if d.run:
                pending.add(self.artifact(s.name).key)
                other = None if self.selection.force else self._same_key_elsewhere(s, d.key)
                if other is not None:
                    d.reason += f"; shared with method {other.method}"
            reports.append(StageReport(s.name, "would run" if d.run else "cached", d.reason))
            self._log_decision(reports[-1])
        return reports

    def run(self) -> list[StageReport]:
        """Execute the selected stages in order; raises :class:`StageFailed` on the first failure."""
        selected = set(self.selection.stages(self.registry))
        self.ws.root.mkdir(parents=True, exist_ok=True)
        reports = []
        for s in self.registry:
            if s.name not in selected:
                continue
            reports.append(self._run_one(s))
        return reports

    def _run_one(self, s: Stage) -> StageReport:
        a = self.artifact(s.name)
        order = self.registry.names()
        # The cross-method inputs present now; one that appears while waiting for the locks is left to the
        # next run (the key records exactly what was read).
        reads = list(self._inputs(s, set()).values())
        with self.ws.lock(a, reads, order, self.lock_timeout_s, write=False):
            d = self._redecide(s)
            if not d.run:
                return self._cached(s, a, d)
        with ExitStack() as held:
            if s.per_method and not self.selection.force:
                # Another method's run may be computing this very artifact (same key) now: wait for it, then
                # share its result. Taken before the stage's locks and released after them (LIFO).
                held.enter_context(
                    self.ws.key_lock(
                        s.name,
                        d.key,
                        self.lock_timeout_s,
                        on_wait=lambda: self.log(
                            f"[{self._where(s.name)}] {s.name:<10} waits     for another method's run computing the "
                            f"same artifact (same cache key), to share it"
                        ),
                    )
                )
            held.enter_context(self.ws.lock(a, reads, order, self.lock_timeout_s))
            d = self._redecide(s)
            if not d.run:
                return self._cached(s, a, d)
            other = None if self.selection.force else self._same_key_elsewhere(s, d.key)
            shared = self._share(s, a, other, d) if other is not None else None
            return shared if shared is not None else self._compute(s, a, d)

    def _compute(self, s: Stage, a: Artifact, d: _Decision) -> StageReport:
        """Run ``s`` into a temporary dir and publish it as ``a`` (decision ``d``; call with its write lock)."""
        report = StageReport(s.name, "run", d.reason)
        self._log_decision(report)
        tmp: Path | None = None
        scratch: Path | None = None
        try:  # the folders too: on a full disk making them is what fails first
            tmp = self.ws.new_tmp_dir(a)
            scratch = self.ws.scratch_dir(a, d.key)
            resumed_s = self.ws.begin_attempt(scratch)
            regular, cross, other_subject = self._context_inputs(s, d.inputs)
            ctx = StageContext(
                cfg=self.cfg,
                subject=self.ws.subject,
                out_dir=tmp,
                inputs=regular,
                scratch_dir=scratch,
                show_progress=self.show_progress,
                method=self.method,
                method_inputs=cross,
                method_problems=self._cross_method_problems(s, d.inputs),
                subject_inputs=other_subject,
                device=self.compute.device if s.device else "cpu",
                precision=self.compute.precision if s.precision else "fp32",
            )
            if s.device:
                self.compute.reset_peak_memory()
            threads = torch_threads()  # before the stage, which may narrow it for a block (avatar.threads)
            with ResourceMonitor() as monitor:
                s.fn(ctx)
            missing = [rel for rel in s.outputs if not (tmp / rel).exists()]
            if missing:
                raise RuntimeError(f"stage did not write its declared output(s) {missing}")
            self._check_inputs_unchanged(s, d)
            usage = monitor.usage
            manifest = Manifest(
                stage=s.name,
                key=d.key,
                version=s.version,
                config=d.config,
                upstream=d.upstream,
                outputs=hash_outputs(tmp),
                # resumed_s: earlier killed runs' work this one resumed from (up to their last checkpoint)
                timings={"wall_s": usage.wall_s, **({"resumed_s": resumed_s} if resumed_s > 0 else {})},
                peak_memory_mb=usage.peak_rss_mb,
                metrics=dict(ctx.metrics),
                git_sha=_git_sha(),
                created=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                sources=d.sources,
                device=self.compute.record(s.precision) if s.device else None,
                threads=threads,
            )
            write_manifest(tmp, manifest)
            self.ws.publish(a, tmp)
            self.ws.discard_scratch(a)
            self._verified[a.key] = manifest
        except BaseException as exc:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
            if scratch is not None:
                self.ws.discard_empty_scratch(scratch)
            if isinstance(exc, KeyboardInterrupt):
                kept = scratch if scratch is not None and scratch.is_dir() else None
                raise Interrupted(s.name, kept) from exc
            written = None if tmp is None else (tmp, self.ws.artifact_dir(a))
            if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
                fix = f"the disk of {self.ws.root} is full: free some space, then run the same command again"
                raise StageFailed(s.name, exc, fix, written) from exc
            if isinstance(exc, Exception):
                raise StageFailed(s.name, exc, written=written) from exc
            raise
        report.wall_s, report.peak_rss_mb, report.metrics = usage.wall_s, usage.peak_rss_mb, dict(ctx.metrics)
        return report

    def _redecide(self, s: Stage) -> _Decision:
        """Decide ``s`` afresh; call holding at least read locks on it and its inputs (no run is writing them)."""
        self._forget_replaced_inputs(self._inputs(s, set()))
        return self._decide(s, self.selection.force, set())

    def _cached(self, s: Stage, a: Artifact, d: _Decision) -> StageReport:
        """The report of cached ``s`` (decision ``d``, under its lock); clears what killed runs of it left."""
        self.ws.discard_leftovers(a)
        report = StageReport(s.name, "cached", d.reason, metrics=self._verified[a.key].metrics)
        self._log_decision(report)
        return report

    def _share(self, s: Stage, a: Artifact, other: Artifact, d: _Decision) -> StageReport | None:
        """Publish ``other``'s artifact (same cache key) as this method's, by hard links, and its manifest
        (the run record: key, timings, metrics) with it; ``None`` when ``other`` is being written right now.

        Its read lock is only tried, never waited for: this run already holds locks, and waiting for one out
        of the DAG order could deadlock with a run that holds it and waits for ours.
        """
        tmp = self.ws.new_tmp_dir(a)
        try:
            with self.ws.read_lock(other):
                manifest = self._readable_manifest(other)
                if (
                    manifest is None
                    or manifest.key != d.key
                    or verify_outputs(self.ws.artifact_dir(other), manifest, s.outputs) is not None
                ):
                    shutil.rmtree(tmp, ignore_errors=True)
                    return None
                self.ws.link_copy(other, tmp)
            self.ws.publish(a, tmp)
            self.ws.discard_scratch(a)
        except LockTimeout:
            shutil.rmtree(tmp, ignore_errors=True)
            return None
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self._verified[a.key] = manifest
        report = StageReport(
            s.name,
            "shared",
            f"{d.reason}; same key as method {other.method}: its artifact is shared, not recomputed",
            metrics=manifest.metrics,
        )
        self._log_decision(report)
        return report

    def _where(self, stage: str) -> str:
        """``<subject>/<method>`` for a per-method stage, else ``<subject>``: how log lines name the artifact."""
        return (
            f"{self.ws.subject}/{self.method}" if self.method and self.registry[stage].per_method else self.ws.subject
        )

    def _log_decision(self, r: StageReport) -> None:
        self.log(f"[{self._where(r.stage)}] {r.stage:<10} {r.action:<9} {r.reason}")


def _input_digest(s: Stage, manifest: Manifest) -> str:
    """What of an input enters ``s``'s key: its outputs, or its whole manifest if ``s`` shows run records."""
    return manifest.record_digest if s.reads_manifests else manifest.output_digest


def _why_key_changed(
    manifest: Manifest, version: str, config: dict[str, Any], upstream: dict[str, str], sources: dict[str, str] | None
) -> str:
    """Human reason for a cache-key mismatch, most specific first."""
    reasons = []
    if sources is not None:
        changed = changed_sources(manifest.sources or {}, sources)
        if changed:
            reasons.append(f"source changed: {', '.join(changed)}")
    if manifest.version != version:
        reasons.append(f"code version changed: {manifest.version} -> {version}")
    keys = changed_keys(manifest.config, config)
    if keys:
        reasons.append(f"config changed: {', '.join(keys)}")
    ups = sorted(k for k in set(manifest.upstream) | set(upstream) if manifest.upstream.get(k) != upstream.get(k))
    if ups:
        reasons.append(f"upstream changed: {', '.join(ups)}")
    return "; ".join(reasons) or "cache key changed"


@functools.lru_cache(maxsize=1)
def _git_sha() -> str:
    """The code's git commit, or 'unknown' outside a checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return out.stdout.strip() or "unknown"


@dataclass(frozen=True)
class RecordedArtifact:
    """An artifact of a finished run as its manifest records it, and why the runner would compute it again (``None``:
    it would not), as :func:`recorded_plan` finds it."""

    artifact: Artifact
    manifest: Manifest | None
    stale: str | None


def recorded_plan(
    ws: Workspace, registry: StageRegistry, target: Artifact, verify: Collection[str] = ()
) -> list[RecordedArtifact]:
    """``target`` and every artifact it is computed from, in the DAG's order, each with the reason the runner would
    compute it again, in :meth:`Runner.plan`'s words, under the settings its own manifest records: ``upstream reruns``
    (an input that is itself stale), no complete artifact, an untrustworthy manifest, a key that is no longer its
    inputs' (``upstream changed``: an input was republished after it was computed) and, for the stages named in
    ``verify`` (hashing reads every file), outputs that are not as recorded. Settings a new command would change are
    not known here, and cross-method inputs keep their recorded digests: this is the plan of what is on disk."""
    wanted = {target.stage} | registry.ancestors(target.stage)
    found: dict[str, RecordedArtifact] = {}
    for s in registry:
        if s.name in wanted:
            a = Artifact(s.name, target.method if s.per_method else None, target.subject)
            found[s.name] = _recorded(ws, s, a, found, s.name in verify)
    return list(found.values())


def _recorded(
    ws: Workspace, s: Stage, a: Artifact, inputs: dict[str, RecordedArtifact], verify: bool
) -> RecordedArtifact:
    """:func:`recorded_plan`'s finding for ``a``, an artifact of ``s``, whose inputs were found as ``inputs`` say; the
    reasons in the order :meth:`Runner._decide` gives them."""
    stage_dir = ws.artifact_dir(a)
    try:
        manifest, unreadable = read_manifest(stage_dir), None
    except ManifestError as exc:
        manifest, unreadable = None, f"manifest corrupted: {exc}"
    rerunning = [name for name in s.inputs if inputs[name].stale is not None]
    if rerunning:
        return RecordedArtifact(a, manifest, f"upstream reruns: {', '.join(rerunning)}")
    if manifest is None:
        missing = "outputs missing" + ("" if stage_dir.exists() else ": never run")
        return RecordedArtifact(a, None, unreadable or missing)
    upstream = dict(manifest.upstream)
    for name in s.inputs:
        found = inputs[name].manifest
        assert found is not None  # an input that is not stale has its manifest
        upstream[name] = _input_digest(s, found)
    if cache_key(s.name, manifest.version, manifest.config, upstream, manifest.sources) != manifest.key:
        why = _why_key_changed(manifest, manifest.version, manifest.config, upstream, manifest.sources)
        return RecordedArtifact(a, manifest, why)
    return RecordedArtifact(a, manifest, verify_outputs(stage_dir, manifest, s.outputs) if verify else None)
