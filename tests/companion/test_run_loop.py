"""``companion run``'s event loop: uvloop's when installed (a pinned dependency), asyncio's own
otherwise, and the flight's coroutine's return code either way."""

from __future__ import annotations

import asyncio
import sys

import pytest

from companion.control.event_loop import run_loop


async def _loop_module() -> int:
    await asyncio.sleep(0)
    return 1 if type(asyncio.get_running_loop()).__module__.startswith("uvloop") else 2


def test_the_companion_runs_on_uvloop() -> None:
    assert run_loop(_loop_module()) == 1


def test_without_uvloop_asyncio_runs_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # an import of it now fails
    assert run_loop(_loop_module()) == 2
