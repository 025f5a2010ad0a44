"""``python -m pipeline.export_ply``: the ``interactavatar-export`` command."""

import sys

from pipeline.export_ply import main

sys.exit(main())
