"""Test-only stages for exercising the runner: a -> b -> c, and a -> d.

Each stage writes a text file derived from its config value and its inputs, so
changing ``stage.<name>.value`` changes that stage's output and all below it.
``stage.<name>.sleep_s`` makes the stage write half its output, then sleep (for kill
tests), then read its inputs a second time and record ``parts/mixed.txt`` if
they changed meanwhile (for tests of concurrent writers); ``stage.<name>.hold_until`` names a file: the stage
waits, after writing half its output, until the test creates it (an ordering that does not depend on the machine's
speed); ``stage.a.fail`` makes it raise after writing half its output;
``stage.a.fail_once`` makes it leave a checkpoint in its scratch dir and
raise, and resume from that checkpoint on the next run; ``stage.<name>.trace``
names a file where start/end times are appended (for
concurrency tests).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.registry import StageRegistry
from pipeline.stage import StageContext, stage


@dataclass
class ToyConfig:
    value: int = 0
    sleep_s: float = 0.0
    hold_until: str | None = None
    fail: bool = False
    fail_once: bool = False
    trace: str | None = None


def _trace(ctx: StageContext, name: str, event: str) -> None:
    trace = ctx.cfg.stage[name].get("trace")
    if trace:
        with open(trace, "a") as f:
            f.write(f"{name} {event} {os.getpid()} {time.time():.6f}\n")


def _toy(name: str, inputs: tuple[str, ...]):
    @stage(
        name, inputs=inputs, config_keys=(f"stage.{name}",), outputs=(f"{name}.txt", "parts"), config_schema=ToyConfig
    )
    def run(ctx: StageContext) -> None:
        """Toy stage: concatenates its inputs with its own value."""
        _trace(ctx, name, "start")
        conf = ctx.cfg.stage[name]
        upstream = "".join(Path(ctx.input_dir(i), f"{i}.txt").read_text() for i in inputs)
        (ctx.out_dir / "parts").mkdir()
        (ctx.out_dir / "parts" / "half.txt").write_text("first half\n")
        if conf.sleep_s:
            time.sleep(conf.sleep_s)
            again = "".join(Path(ctx.input_dir(i), f"{i}.txt").read_text() for i in inputs)
            if again != upstream:
                (ctx.out_dir / "parts" / "mixed.txt").write_text(f"first read:\n{upstream}second read:\n{again}")
        while conf.hold_until and not Path(conf.hold_until).exists():
            time.sleep(0.05)
        if conf.fail:
            raise RuntimeError(f"toy stage {name} was told to fail")
        checkpoint = ctx.scratch_dir / "checkpoint.txt"
        if conf.fail_once and not checkpoint.exists():
            checkpoint.write_text("half done\n")
            raise RuntimeError(f"toy stage {name} failed after a checkpoint")
        if checkpoint.exists():
            (ctx.out_dir / "parts" / "resumed.txt").write_text(checkpoint.read_text())
        (ctx.out_dir / f"{name}.txt").write_text(f"{upstream}{name}={conf.value}\n")
        ctx.metrics["value"] = int(conf.value)
        _trace(ctx, name, "end")

    return run


REGISTRY = StageRegistry([_toy("a", ()), _toy("b", ("a",)), _toy("c", ("b",)), _toy("d", ("a",))])
