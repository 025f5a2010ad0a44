"""The defaults in ``conf/`` of the settings the core's config dataclasses define, generated from the dataclasses.

Each such setting is defined once, in its dataclass (the training loops' WarmupTrainConfig, DynamicTrainConfig and
SplattingConfig, the model's DynamicModelConfig, the fitting's FitConfig and RefineConfig, the evaluation's
AvatarTrackingConfig, the contact solver's PBDConfig, the viewer's CodecConfig): its name, type, default and
documentation (the comment at or above its field). The YAML files hold a generated block of those defaults and
comments between two marker lines, beside the settings of their own (the stages' own, and where the pipeline chooses
otherwise: checkpoints, the run's seed). ``python -m avatar.config_defaults`` rewrites the blocks; ``--check`` fails
where one is out of date, as ``tests/test_config_schemas.py`` does. The config reference
(``pipeline.config_reference``) reads the YAML, so it shows the dataclasses' words.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from avatar.fitting.fit import FitConfig
from avatar.fitting.refine import RefineConfig
from avatar.pbd import PBDConfig
from avatar.representations.bound.dynamic_model import DynamicModelConfig
from avatar.representations.bound.representation import PRESET_ARCHITECTURE
from avatar.representations.bound.stage_two import DynamicTrainConfig
from avatar.representations.bound.warmup import WarmupTrainConfig
from avatar.representations.embedded.representation import SHARED_SCHEDULE
from avatar.representations.embedded.training import SplattingConfig
from avatar.training.avatar_tracking import AvatarTrackingConfig
from avatar.training.frame_params import ParamLearningRates
from avatar.viewer.codec import CodecConfig
from data_schemas.config_sections import with_generated_block

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
#: the settings whose YAML default the pipeline chooses itself (written by hand beside the block, with why)
PIPELINE_CHOICES = ("checkpoint_every", "seed")


@dataclass(frozen=True)
class GeneratedDefaults:
    """A block of ``file`` (relative to ``conf/``) generated from ``core``'s fields less ``exclude``."""

    file: str
    core: type
    exclude: tuple[str, ...]


BLOCKS = (
    GeneratedDefaults("stage/warmup.yaml", WarmupTrainConfig, ("steps", *PIPELINE_CHOICES)),
    GeneratedDefaults("stage/warmup.yaml", ParamLearningRates, ()),
    GeneratedDefaults("stage/dynamic.yaml", DynamicModelConfig, PRESET_ARCHITECTURE),
    GeneratedDefaults("stage/dynamic.yaml", DynamicTrainConfig, ("steps", "selection", *PIPELINE_CHOICES)),
    GeneratedDefaults("config.yaml", SplattingConfig, SHARED_SCHEDULE),
    GeneratedDefaults("stage/fit.yaml", FitConfig, ("face_shape_columns",)),
    GeneratedDefaults("stage/fit.yaml", RefineConfig, ()),
    GeneratedDefaults("stage/evaluate.yaml", AvatarTrackingConfig, ()),
    GeneratedDefaults("stage/pbd.yaml", PBDConfig, ()),
    GeneratedDefaults("stage/viewer.yaml", CodecConfig, ()),
)


def rendered(conf_dir: Path = CONF_DIR) -> dict[Path, str]:
    """file -> its text with every generated block rewritten from its dataclass."""
    texts: dict[Path, str] = {}
    for block in BLOCKS:
        path = conf_dir / block.file
        text = texts.get(path, path.read_text())
        texts[path] = with_generated_block(text, block.core, block.exclude, where=str(path))
    return texts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--check", action="store_true", help="fail if a block is out of date, write nothing")
    args = parser.parse_args(argv)
    stale = [path for path, text in rendered().items() if path.read_text() != text]
    if args.check:
        for path in stale:
            print(f"{path}: its generated defaults are out of date; run python -m avatar.config_defaults")
        return 1 if stale else 0
    for path, text in rendered().items():
        if path in stale:
            path.write_text(text)
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
