"""The smoke DAG's artifact digests, to show that a change which should not alter any output alters none.

Run it on the commit before a refactor and on the commit after, then compare::

    python -m tests.smoke_digests run /tmp/before.json            # on the old commit
    python -m tests.smoke_digests run /tmp/after.json             # on the new one
    python -m tests.smoke_digests compare /tmp/before.json /tmp/after.json

``run`` runs the whole DAG at ``quality=smoke`` for one method of each representation and for the
GaussianAvatars baseline (``--methods``) through the CLI into a fresh directory, then reads every stage's
manifest: the sha256 of each output file (the manifest's own record, checked against the bytes) and the
stage's cache key. Files that record when or how fast something ran (the report's page, timing logs) differ
between any two runs and are listed apart by name, never compared. ``compare`` prints every difference and
exits 1 when there is one.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from pipeline.manifest import MANIFEST_NAME, sha256_file
from tests.conftest import REPO, cli_command, cli_env

#: one method per representation (bound with every module, embedded) and the static baseline
DEFAULT_METHODS = ("interactavatar", "gaussian_avatars", "splatting_avatar")
#: output files whose bytes carry wall times or dates, so two runs of the same code never agree on them
TIMED = ("report.html", "report.md", "timings.json", "train_log.parquet", "profile.json")


def collect(outputs: Path) -> dict[str, dict[str, str]]:
    """``{"files": {path: sha256}, "keys": {stage dir: cache key}, "timed": {path: ""}}`` of every manifest below
    ``outputs``; paths relative to ``outputs``. A file whose bytes disagree with its manifest is an error."""
    files: dict[str, str] = {}
    keys: dict[str, str] = {}
    timed: dict[str, str] = {}
    for manifest_path in sorted(outputs.rglob(MANIFEST_NAME)):
        stage_dir = manifest_path.parent
        manifest = json.loads(manifest_path.read_text())
        keys[stage_dir.relative_to(outputs).as_posix()] = manifest["key"]
        for rel, digest in sorted(manifest["outputs"].items()):
            path = stage_dir / rel
            if sha256_file(path) != digest:
                raise SystemExit(f"{path}: its bytes disagree with {manifest_path}; rerun on a fresh directory")
            name = (stage_dir / rel).relative_to(outputs).as_posix()
            (timed if Path(rel).name in TIMED else files)[name] = "" if Path(rel).name in TIMED else digest
    return {"files": files, "keys": keys, "timed": timed}


def run(destination: Path, methods: list[str], workdir: Path | None) -> None:
    """Run the smoke DAG for each method into a fresh directory and write its digests to ``destination``."""
    root = Path(tempfile.mkdtemp(prefix="smoke-digests-", dir=workdir))
    for method in methods:
        done = subprocess.run(
            cli_command(f"paths.outputs={root}", "quality=smoke", f"method={method}", "run.progress=false"),
            cwd=REPO,
            env=cli_env(),
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
    compare_parser = sub.add_parser("compare", help="compare two digest files; exit 1 on any difference")
    compare_parser.add_argument("before", type=Path)
    compare_parser.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    if args.command == "run":
        run(args.destination, args.methods, args.workdir)
        return 0
    differences = compare(json.loads(args.before.read_text()), json.loads(args.after.read_text()))
    print("\n".join(differences) if differences else "identical: every file and every cache key")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main())
