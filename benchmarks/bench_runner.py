"""Runner overhead: a fully cached run against the first run, in-process and through the CLI.

Prints two tables:

1. a synthetic chain of stages writing many files (the cost of hashing and
   verifying artifacts when everything is cached), in-process;
2. the real DAG at ``quality=smoke`` through the ``interactavatar`` CLI, with the
   interpreter-and-import start-up measured separately so the runner's own
   overhead is visible. Goal: cached run < 2 s plus start-up.

The tables are appended to ``benchmarks/results/bench_runner.json`` (``--results``) with the commit and the
machine.

Usage: python benchmarks/bench_runner.py [--stages 10] [--files 50] [--kb 256] [--skip-cli] [--results DIR]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from hydra import compose, initialize_config_dir  # noqa: E402

from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from pipeline.config import validate_config  # noqa: E402
from pipeline.registry import StageRegistry  # noqa: E402
from pipeline.runner import Runner  # noqa: E402
from pipeline.stage import StageContext, stage  # noqa: E402


def _payload_stage(name: str, inputs: tuple[str, ...], files: int, kb: int):
    @stage(name, inputs=inputs, outputs=("data",))
    def run(ctx: StageContext) -> None:
        (ctx.out_dir / "data").mkdir()
        block = (name.encode() * (kb * 1024 // len(name) + 1))[: kb * 1024]
        for i in range(files):
            (ctx.out_dir / "data" / f"{i:04d}.bin").write_bytes(block)

    return run


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench_in_process(n_stages: int, files: int, kb: int) -> list[tuple]:
    chain = [_payload_stage(f"s{i}", (f"s{i - 1}",) if i else (), files, kb) for i in range(n_stages)]
    registry = StageRegistry(chain)
    with tempfile.TemporaryDirectory() as tmp, initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["stage=[]", f"paths.outputs={tmp}", "run.progress=false"])
        cfg = validate_config(cfg, registry)
        quiet = lambda _msg: None  # noqa: E731
        first = _timed(lambda: Runner(cfg, registry, log=quiet).run())
        cached = _timed(lambda: Runner(cfg, registry, log=quiet).run())
    total_mb = n_stages * files * kb / 1024
    return [(f"{n_stages} stages x {files} files x {kb} KiB ({total_mb:.0f} MiB)", first, cached, cached / first)]


def bench_cli() -> list[tuple]:
    env_cmd = [sys.executable]
    with tempfile.TemporaryDirectory() as tmp:
        args = ["-m", "pipeline.cli", f"paths.outputs={tmp}", "quality=smoke", "run.progress=false"]
        startup = _timed(lambda: subprocess.run([*env_cmd, "-c", "import pipeline.cli, stages"], cwd=REPO, check=True))
        first = _timed(lambda: subprocess.run([*env_cmd, *args], cwd=REPO, check=True, capture_output=True))
        cached = _timed(lambda: subprocess.run([*env_cmd, *args], cwd=REPO, check=True, capture_output=True))
    return [("real DAG, quality=smoke, CLI", first, cached, cached / first, startup, cached - startup)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stages", type=int, default=10)
    parser.add_argument("--files", type=int, default=50)
    parser.add_argument("--kb", type=int, default=256)
    parser.add_argument("--skip-cli", action="store_true")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_runner")
    rows = bench_in_process(args.stages, args.files, args.kb)
    print(
        log.table(
            "synthetic chain, in-process",
            ("workload (in-process)", "first run s", "cached run s", "cached / first"),
            rows,
        )
    )
    if not args.skip_cli:
        print()
        print(
            log.table(
                "the real DAG through the CLI",
                (
                    "workload",
                    "first run s",
                    "cached run s",
                    "cached / first",
                    "start-up s",
                    "runner overhead s (goal < 2)",
                ),
                bench_cli(),
            )
        )
    log.write(args.results)


if __name__ == "__main__":
    main()
