"""Procedural MANO / FLAME stand-ins, built in code (no licensed files needed).

Both return a :class:`TemplateModel` with exactly the fields of the official
models, so every layer and stage runs out of the box. They are deterministic and
cached: every call returns the same (read-only) object.
"""

from __future__ import annotations

from functools import lru_cache

from avatar.templates.hand import build_hand
from avatar.templates.head import build_head
from avatar.templates.model import TemplateModel


@lru_cache(maxsize=1)
def procedural_hand() -> TemplateModel:
    """Right hand, MANO layout: 16 joints, 10 betas, 45-D pose with a PCA basis."""
    return build_hand()


@lru_cache(maxsize=1)
def procedural_head() -> TemplateModel:
    """Head and neck, FLAME layout: 5 joints, 217 identity (10 designed) + 10 expression columns, 68 landmarks."""
    return build_head()
