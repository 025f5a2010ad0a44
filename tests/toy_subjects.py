"""Test-only DAG reading another subject: ``a`` per subject, ``drive`` reads its own ``a`` and, when
``stage.drive.driver`` names another subject, that subject's ``a`` (like a reenactment's driver ``fit``)."""

from __future__ import annotations

from omegaconf import DictConfig

from pipeline.registry import StageRegistry
from pipeline.stage import StageContext, stage


@stage("a", config_keys=("stage.a",), outputs=("a.txt",))
def a(ctx: StageContext) -> None:
    """Per-subject root."""
    (ctx.out_dir / "a.txt").write_text(f"{ctx.subject}: a={ctx.cfg.stage.a.value}\n")


def driver(cfg: DictConfig) -> str | None:
    name = cfg.stage.drive.driver
    return None if name == "self" else str(name)


@stage(
    "drive",
    inputs=("a",),
    config_keys=("stage.drive",),
    outputs=("drive.txt",),
    subject_inputs=("a",),
    input_subject=driver,
)
def drive(ctx: StageContext) -> None:
    """Own ``a`` driven by the other subject's."""
    own = (ctx.input_dir("a") / "a.txt").read_text()
    other = (ctx.subject_input_dir("a") / "a.txt").read_text() if driver(ctx.cfg) else "self\n"
    (ctx.out_dir / "drive.txt").write_text(own + other)


REGISTRY = StageRegistry([a, drive])
