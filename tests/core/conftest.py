"""Fixtures shared by the core's tests: the default config and its terminal design (a test
module that needs other parameters defines its own ``cfg``)."""

from __future__ import annotations

import pytest

from companion.config import Config, load_config
from companion.core.design import design_terminal
from companion.core.terminal import TerminalDesign


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config()


@pytest.fixture(scope="module")
def design(cfg: Config) -> TerminalDesign:
    return design_terminal(cfg.rmpc, cfg.camera)
