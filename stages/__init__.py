"""The real stages of the pipeline, registered in DAG order."""

from pipeline.registry import StageRegistry
from stages.capture import capture
from stages.frames import frames
from stages.report import report

REGISTRY = StageRegistry([capture, frames, report])
