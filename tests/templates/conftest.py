"""Fixtures for the template tests: the two procedural models (built once)."""

from __future__ import annotations

import pytest

from avatar.templates import TemplateModel, procedural_hand, procedural_head


@pytest.fixture(scope="session")
def hand() -> TemplateModel:
    return procedural_hand()


@pytest.fixture(scope="session")
def head() -> TemplateModel:
    return procedural_head()
