"""The real stages of the pipeline, registered in DAG order."""

from pipeline.registry import StageRegistry
from stages.capture import capture
from stages.evaluate import evaluate
from stages.frames import frames
from stages.report import report
from stages.warmup import warmup

REGISTRY = StageRegistry([capture, frames, warmup, evaluate, report])
