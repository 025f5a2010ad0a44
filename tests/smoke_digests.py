"""The smoke DAG's artifact digests, to show that a change which should not alter any output alters none.

Run it on the commit before a refactor and on the commit after, then compare::

    python -m tests.smoke_digests run /tmp/before.json --commit HEAD~3
    python -m tests.smoke_digests run /tmp/after.json --commit HEAD
    python -m tests.smoke_digests compare /tmp/before.json /tmp/after.json

``--commit`` runs a clean clone of that commit, always at the same path (some cache keys name the checkout's files,
e.g. the viewer's page), so the two runs differ only by their code; without it the working tree runs as it is.

``run`` runs the whole DAG at ``quality=smoke`` for one method of each representation and for the GaussianAvatars
baseline (``--methods``) through the CLI into a fresh directory, then reads every stage's manifest: the sha256 of
each output file (the manifest's own record, checked against the bytes) and the stage's cache key. Files that record
when or how fast something ran (the report's page, the comparison's text tables) differ between any two runs and are
listed apart by name, never compared; a Parquet table with a wall-time column (the comparison's ``train_wall_s``) is
compared without it. The cache keys of the stages that show their inputs' run records (compare, report: their keys
cover those manifests' timings and commit) are listed apart the same way. ``compare`` prints every difference and
exits 1 when there is one.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pyarrow.parquet as pq

from pipeline.manifest import MANIFEST_NAME, sha256_file
from stages import REGISTRY
from tests.conftest import REPO, cli_command

#: one method per representation (bound with every module, embedded) and the static baseline
DEFAULT_METHODS = ("interactavatar", "gaussian_avatars", "splatting_avatar")
#: output files whose bytes carry wall times or dates, so two runs of the same code never agree on them
TIMED = ("report.html", "tables.json", "tables.md")
#: columns of a Parquet output that hold wall times: the table is compared without them
WALL_TIME_COLUMNS = ("train_wall_s",)


def content_digest(path: Path, digest: str) -> str:
    """A file's digest as compared: its sha256 ``digest``; for a Parquet table with wall-time columns, the sha256 of
    its values without them."""
    if path.suffix == ".parquet":
        table = pq.read_table(path)
        timed = [c for c in WALL_TIME_COLUMNS if c in table.column_names]
        if timed:
            return hashlib.sha256(json.dumps(table.drop_columns(timed).to_pydict(), default=str).encode()).hexdigest()
    return digest


def collect(outputs: Path) -> dict[str, dict[str, str]]:
    """``{"files": {path: sha256}, "keys": {stage dir: cache key}, "timed": {path: ""}}`` of every manifest below
    ``outputs``; paths relative to ``outputs``. A file whose bytes disagree with its manifest is an error."""
    files: dict[str, str] = {}
    keys: dict[str, str] = {}
    timed: dict[str, str] = {}
    for manifest_path in sorted(outputs.rglob(MANIFEST_NAME)):
        stage_dir = manifest_path.parent
        manifest = json.loads(manifest_path.read_text())
        where = stage_dir.relative_to(outputs).as_posix()
        if REGISTRY[manifest["stage"]].reads_manifests:
            timed[f"key of {where}"] = ""
        else:
            keys[where] = manifest["key"]
        for rel, digest in sorted(manifest["outputs"].items()):
            path = stage_dir / rel
            if sha256_file(path) != digest:
                raise SystemExit(f"{path}: its bytes disagree with {manifest_path}; rerun on a fresh directory")
            name = path.relative_to(outputs).as_posix()
            if Path(rel).name in TIMED:
                timed[name] = ""
            else:
                files[name] = content_digest(path, digest)
    return {"files": files, "keys": keys, "timed": timed}


def checkout(commit: str, workdir: Path | None) -> Path:
    """A clean clone of this repository at ``commit``, always at ``<workdir>/smoke-digests-checkout``."""
    path = Path(workdir or tempfile.gettempdir()) / "smoke-digests-checkout"
    shutil.rmtree(path, ignore_errors=True)
    subprocess.run(["git", "clone", "-q", str(REPO), str(path)], check=True)
    subprocess.run(["git", "-C", str(path), "checkout", "-q", commit], check=True)
    return path


def run(destination: Path, methods: list[str], workdir: Path | None, commit: str | None, overrides: list[str]) -> None:
    """Run the smoke DAG for each method into a fresh directory and write its digests to ``destination``."""
    code = checkout(commit, workdir) if commit else REPO
    env = {**os.environ, "PYTHONPATH": str(code), "PYTHONUNBUFFERED": "1"}
    root = Path(tempfile.mkdtemp(prefix="smoke-digests-", dir=workdir))
    for method in methods:
        done = subprocess.run(
            cli_command(f"paths.outputs={root}", "quality=smoke", f"method={method}", "run.progress=false", *overrides),
            cwd=code,
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode != 0:
            raise SystemExit(f"method={method} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    digests = collect(root)
    digests["methods"] = {m: "" for m in methods}
    destination.write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
    print(f"{len(digests['files'])} files, {len(digests['keys'])} stages -> {destination} (outputs in {root})")


def compare(before: dict[str, dict[str, str]], after: dict[str, dict[str, str]]) -> list[str]:
    """One line per difference: a file or stage present in one run only, or a digest or cache key that changed."""
    lines: list[str] = []
    for section in ("files", "keys", "timed"):
        old, new = before.get(section, {}), after.get(section, {})
        lines += [f"{section}: only before: {k}" for k in sorted(old.keys() - new.keys())]
        lines += [f"{section}: only after: {k}" for k in sorted(new.keys() - old.keys())]
        lines += [f"{section}: changed: {k}" for k in sorted(old.keys() & new.keys()) if old[k] != new[k]]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run_parser = sub.add_parser("run", help="run the smoke DAG and write its digests")
    run_parser.add_argument("destination", type=Path)
    run_parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    run_parser.add_argument("--workdir", type=Path, default=None, help="where the outputs go (default: the temp dir)")
    run_parser.add_argument("--commit", default=None, help="run a clean clone of this commit (default: the tree)")
    run_parser.add_argument("--overrides", nargs="*", default=[], help="more config overrides for every run")
    compare_parser = sub.add_parser("compare", help="compare two digest files; exit 1 on any difference")
    compare_parser.add_argument("before", type=Path)
    compare_parser.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    if args.command == "run":
        run(args.destination, args.methods, args.workdir, args.commit, args.overrides)
        return 0
    differences = compare(json.loads(args.before.read_text()), json.loads(args.after.read_text()))
    print("\n".join(differences) if differences else "identical: every file and every cache key")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main())
