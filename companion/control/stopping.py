"""The companion's stop request: SIGINT / SIGTERM, the flight's duration or a lost camera set
it; the control loop then leaves OFFBOARD and exits (:mod:`companion.control.runtime`)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable, Iterator


class StopRequested(Exception):
    """A stop was requested (signal, duration) while waiting for a camera frame."""


class StopEvent(asyncio.Event):
    """The companion's stop request: an ``asyncio.Event`` whose :meth:`set` also calls
    ``on_set`` (the control loop's frame wait then ends at once, see
    ``CompanionApp._next_frame``)."""

    def __init__(self, on_set: Callable[[], None]) -> None:
        super().__init__()
        self._on_set = on_set

    def set(self) -> None:
        super().set()
        self._on_set()


@contextlib.contextmanager
def stop_on_signals(stop: asyncio.Event) -> Iterator[None]:
    """SIGINT / SIGTERM set ``stop`` (the control loop then leaves OFFBOARD and exits)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    try:
        yield
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.remove_signal_handler(sig)
