"""``interactavatar-export`` carried out: the parsed command line exported, and what stops it said in one line."""

from __future__ import annotations

import argparse
import sys

from avatar.artifacts import HELD_OUT_SEQUENCE
from avatar.templates.loaders import OfficialModelError
from data_schemas.tables import SchemaError
from pipeline.device import DeviceUnavailable, resolve_device
from pipeline.export_ply.frames import export_motion
from pipeline.export_ply.options import PROG, ExportError
from pipeline.export_ply.trained import open_run

#: how a setting of the pipeline's that an error names is given to the export
_OPTIONS = {"run.device=": "--device ", "model.flame_path=": "--flame-path ", "model.mano_path=": "--mano-path "}


def run(args: argparse.Namespace, lock_wait_s: float) -> int:
    """Export what ``args`` asks (:func:`pipeline.export_ply.options.parser`), waiting ``lock_wait_s`` seconds at
    most for a run that is rewriting what it reads: 0, or 2 with one line on stderr."""
    progress = None if args.quiet else _say
    try:
        device = resolve_device(args.device)
        with open_run(
            args.subject,
            args.method,
            args.seed,
            placement=args.placement,
            flame_path=args.flame_path,
            mano_path=args.mano_path,
            lock_wait_s=lock_wait_s,
        ) as trained:
            motion = HELD_OUT_SEQUENCE if args.motion is None else args.motion
            written = export_motion(
                trained,
                motion,
                args.out,
                frames=args.frames,
                axes=args.axes,
                overwrite=args.overwrite,
                progress=progress,
                device=device,
            )
    except (DeviceUnavailable, OfficialModelError) as exc:  # their messages name the pipeline's settings
        return _fail(_as_options(str(exc)))
    except (ExportError, SchemaError, OSError) as exc:
        return _fail(str(exc))
    print(f"{len(written)} PLY files ({args.axes} axes) in {args.out}")
    return 0


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _as_options(message: str) -> str:
    """``message`` with the pipeline's settings it names (``run.device=``, ``model.flame_path=``) put as the export's
    options that give them."""
    for setting, option in _OPTIONS.items():
        message = message.replace(setting, option)
    return message


def _fail(message: str) -> int:
    """Print ``message``'s first line after the command's name; exit status 2."""
    _say(f"{PROG}: {message.splitlines()[0] if message.strip() else 'failed'}")
    return 2
