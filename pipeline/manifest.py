"""Content hashes, cache keys, and the per-stage ``_manifest.json``.

The manifest is the last file written into a stage directory. It records the
cache key, the config subset and upstream digests that produced it, the sha256
of every output file, timings and metrics. It also carries a digest of its own
content, so a hand-edited or truncated manifest is detected like a corrupted
output file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from data_schemas.writes import write_json

MANIFEST_NAME = "_manifest.json"
MANIFEST_VERSION = 1
_CHUNK = 1 << 20


def sha256_file(path: Path) -> str:
    """sha256 hex digest of a file's bytes (streamed)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def canonical_json(obj: Any) -> str:
    """Deterministic JSON text (sorted keys, no whitespace) used for every hash."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def sha256_json(obj: Any) -> str:
    return hashlib.sha256(canonical_json(obj).encode()).hexdigest()


def hash_outputs(stage_dir: Path) -> dict[str, str]:
    """relative posix path -> sha256 for every file below ``stage_dir`` except the manifest."""
    files = sorted(p for p in stage_dir.rglob("*") if p.is_file() and p.name != MANIFEST_NAME)
    return {p.relative_to(stage_dir).as_posix(): sha256_file(p) for p in files}


def cache_key(
    stage: str, version: str, config: dict[str, Any], upstream: dict[str, str], sources: dict[str, str] | None = None
) -> str:
    """sha256 over the stage name, its code version, its config subset, the upstream output digests and,
    for stages that import user files, those files' digests."""
    body: dict[str, Any] = {"stage": stage, "version": version, "config": config, "upstream": upstream}
    if sources is not None:
        body["sources"] = sha256_json(sources)
    return sha256_json(body)


@dataclass
class Manifest:
    """In-memory form of ``_manifest.json``."""

    stage: str
    key: str
    version: str
    config: dict[str, Any]
    upstream: dict[str, str]
    outputs: dict[str, str]
    timings: dict[str, float]
    peak_memory_mb: float
    metrics: dict[str, Any]
    git_sha: str
    created: str
    sources: dict[str, str] | None = None  # relative path -> sha256 of imported user files
    device: dict[str, Any] | None = None  # a device stage's: kind, name (model), precision, peak_memory_mb (CUDA)
    threads: int | None = None  # the CPU threads torch computed on (run.threads); None where no stage loaded torch

    @property
    def output_digest(self) -> str:
        """One hash standing for all outputs; downstream cache keys depend on it."""
        return sha256_json(self.outputs)

    @property
    def record_digest(self) -> str:
        """One hash of the whole manifest (outputs and the run's timings, metrics, date), for stages that show them."""
        return sha256_json(self.to_json())

    def to_json(self) -> dict[str, Any]:
        body: dict[str, Any] = {
            "manifest_version": MANIFEST_VERSION,
            "stage": self.stage,
            "key": self.key,
            "version": self.version,
            "config": self.config,
            "upstream": self.upstream,
            "outputs": self.outputs,
            "output_digest": self.output_digest,
            "timings": self.timings,
            "peak_memory_mb": self.peak_memory_mb,
            "metrics": self.metrics,
            "git_sha": self.git_sha,
            "created": self.created,
        }
        if self.sources is not None:
            body["sources"] = self.sources
        if self.device is not None:
            body["device"] = self.device
        if self.threads is not None:
            body["threads"] = self.threads
        body["manifest_digest"] = sha256_json(body)
        return body


class ManifestError(ValueError):
    """A manifest exists but cannot be trusted."""


def write_manifest(stage_dir: Path, manifest: Manifest) -> None:
    """Write the manifest (callers write it last, inside the temporary stage dir)."""
    write_json(stage_dir / MANIFEST_NAME, manifest.to_json(), "manifest")


def read_manifest(stage_dir: Path) -> Manifest | None:
    """The stage's manifest, ``None`` if there is none; :class:`ManifestError` if it was tampered with."""
    path = stage_dir / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        body = json.loads(path.read_text())
        claimed = body.pop("manifest_digest")
    except (json.JSONDecodeError, KeyError, AttributeError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: unreadable manifest ({exc})") from exc
    if sha256_json(body) != claimed:
        raise ManifestError(f"{path}: manifest content does not match its digest (edited or corrupted)")
    if body.get("manifest_version") != MANIFEST_VERSION:
        raise ManifestError(f"{path}: manifest version {body.get('manifest_version')} != {MANIFEST_VERSION}")
    return Manifest(
        stage=body["stage"],
        key=body["key"],
        version=body["version"],
        config=body["config"],
        upstream=body["upstream"],
        outputs=body["outputs"],
        timings=body["timings"],
        peak_memory_mb=body["peak_memory_mb"],
        metrics=body["metrics"],
        git_sha=body["git_sha"],
        created=body["created"],
        sources=body.get("sources"),
        device=body.get("device"),
        threads=body.get("threads"),
    )


def verify_outputs(stage_dir: Path, manifest: Manifest, declared: tuple[str, ...]) -> str | None:
    """Why the outputs on disk are not whole, or ``None`` when they match the manifest.

    Checks that every declared output exists, that no recorded file is missing or
    extra, and that every file's content hash matches.
    """
    for rel in declared:
        if not (stage_dir / rel).exists():
            return f"outputs missing: {rel}"
    on_disk = sorted(
        p.relative_to(stage_dir).as_posix() for p in stage_dir.rglob("*") if p.is_file() and p.name != MANIFEST_NAME
    )
    recorded = sorted(manifest.outputs)
    if on_disk != recorded:
        missing = sorted(set(recorded) - set(on_disk))
        extra = sorted(set(on_disk) - set(recorded))
        return f"outputs missing: {missing[0]}" if missing else f"outputs changed: unexpected file {extra[0]}"
    for rel, digest in manifest.outputs.items():
        if sha256_file(stage_dir / rel) != digest:
            return f"outputs corrupted: {rel} (hash mismatch)"
    return None
