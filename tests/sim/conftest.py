from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.sim.harness import MavClient


@pytest.fixture
def client() -> Iterator[MavClient]:
    c = MavClient()
    yield c
    c.close()
