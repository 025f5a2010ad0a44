"""Test-only DAG with per-method stages: a -> p -> q, and cmp reading q of several methods.

- ``a`` is shared by every method;
- ``p`` is per-method and depends on ``method.p_value`` only, so methods with the same value have the same
  ``p`` (the runner shares it instead of recomputing);
- ``q`` is per-method and depends on ``method.name`` and ``seed`` (every run its own);
- ``cmp`` is shared and reads ``q`` of the methods listed in ``stage.cmp.methods`` that exist, one run per seed
  of ``stage.cmp.seeds``.

For concurrency tests (none of these enter a key): ``method.sleep_s`` makes ``p`` and ``q`` sleep that long, and
``method.trace`` names a file where ``p`` and ``q`` append ``<stage> <method> start|end <time>`` lines.
"""

from __future__ import annotations

import time
from pathlib import Path

from pipeline.registry import StageRegistry
from pipeline.stage import StageContext, stage


@stage("a", config_keys=("stage.a",), outputs=("a.txt",))
def a(ctx: StageContext) -> None:
    """Shared root."""
    (ctx.out_dir / "a.txt").write_text(f"a={ctx.cfg.stage.a.value}\n")


def _trace(ctx: StageContext, name: str, event: str) -> None:
    trace = ctx.cfg.method.get("trace")
    if trace:
        with open(trace, "a") as f:
            f.write(f"{name} {ctx.method} {event} {time.time():.6f}\n")
    if event == "start":
        time.sleep(float(ctx.cfg.method.get("sleep_s", 0.0)))  # after "start": the traced interval holds it


@stage("p", inputs=("a",), config_keys=("method.p_value",), outputs=("p.txt",), per_method=True)
def p(ctx: StageContext) -> None:
    """Per-method stage that only some method keys change."""
    _trace(ctx, "p", "start")
    text = (ctx.input_dir("a") / "a.txt").read_text()
    (ctx.out_dir / "p.txt").write_text(f"{text}p={ctx.cfg.method.p_value}\n")
    _trace(ctx, "p", "end")


@stage("q", inputs=("p",), config_keys=("method.name", "seed"), outputs=("q.txt",), per_method=True)
def q(ctx: StageContext) -> None:
    """Per-method stage of every method its own."""
    _trace(ctx, "q", "start")
    text = (ctx.input_dir("p") / "p.txt").read_text()
    (ctx.out_dir / "q.txt").write_text(f"{text}q={ctx.method}\n")
    _trace(ctx, "q", "end")


@stage(
    "cmp",
    config_keys=("stage.cmp",),
    outputs=("cmp.txt",),
    cross_method_inputs=("q",),
    methods_key="stage.cmp.methods",
    seeds_key="stage.cmp.seeds",
)
def cmp(ctx: StageContext) -> None:
    """Shared stage reading every listed method's q (and naming the listed ones whose q is on disk but unusable)."""
    dirs = ctx.method_dirs("q")
    read = "".join(f"{m}: {Path(d, 'q.txt').read_text()}" for m, d in sorted(dirs.items()))
    unusable = "".join(f"unusable {m}: {why}\n" for m, why in ctx.method_problems.items())
    (ctx.out_dir / "cmp.txt").write_text(read + unusable)
    ctx.metrics["methods"] = len(dirs)


REGISTRY = StageRegistry([a, p, q, cmp])
