"""The real stages of the pipeline, registered in DAG order."""

from pipeline.registry import StageRegistry
from stages.capture import capture
from stages.compare import compare
from stages.dynamic import dynamic
from stages.evaluate import evaluate
from stages.fit import fit
from stages.frames import frames
from stages.keypoints import keypoints
from stages.pbd import pbd
from stages.reenact import reenact
from stages.report import report
from stages.scene import scene
from stages.viewer import viewer
from stages.warmup import warmup

REGISTRY = StageRegistry(
    [capture, frames, keypoints, fit, scene, pbd, warmup, dynamic, evaluate, compare, reenact, viewer, report]
)
