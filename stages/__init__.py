"""The real stages of the pipeline, registered in DAG order."""

from pipeline.registry import StageRegistry

REGISTRY = StageRegistry([])
