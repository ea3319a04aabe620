"""Suite-wide settings and fixtures. Hypothesis' per-example deadline (200 ms) is a timed
assertion: on a loaded 2-core CI machine it failed property tests that were correct. Speed lives
in bench/. ``cfg`` / ``design``: the default config and its terminal design (a test module that
needs other parameters defines its own ``cfg``)."""

from __future__ import annotations

import pytest
from hypothesis import settings

from companion.config import Config, load_config
from companion.core.design import design_terminal
from companion.core.terminal import TerminalDesign

settings.register_profile("suite", deadline=None)
settings.load_profile("suite")


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config()


@pytest.fixture(scope="module")
def design(cfg: Config) -> TerminalDesign:
    return design_terminal(cfg.rmpc, cfg.camera)
