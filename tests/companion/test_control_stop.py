"""The control loop's frame wait (``CompanionApp._next_frame``): a frame, a timeout, and a stop
request that ends the wait at once (the wait runs in the control task under one
``asyncio.timeout``; :class:`companion.control.stopping.StopEvent` moves it to now)."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from companion.control.runtime import CompanionApp
from companion.control.stopping import StopEvent, StopRequested


class _Frames:
    """A camera whose next frame arrives when :meth:`deliver` is called."""

    def __init__(self) -> None:
        self.pending: asyncio.Future[Any] | None = None
        self.cancelled = 0

    def __aiter__(self) -> _Frames:
        return self

    async def __anext__(self) -> Any:
        self.pending = asyncio.get_running_loop().create_future()
        try:
            return await self.pending
        except asyncio.CancelledError:
            self.cancelled += 1
            raise

    def deliver(self, frame: Any) -> None:
        assert self.pending is not None
        self.pending.set_result(frame)


def _app() -> CompanionApp:
    app = CompanionApp.__new__(CompanionApp)  # the wait needs only its stop and its deadline
    app._stop = StopEvent(app._wake_frame_wait)
    app._frame_wait = None
    return app


def test_a_frame_is_returned_and_the_wait_forgotten() -> None:
    async def main() -> None:
        app, cam = _app(), _Frames()
        asyncio.get_running_loop().call_soon(cam.deliver, "frame")
        assert await app._next_frame(cam, 5.0, wake_on_stop=True) == "frame"
        assert app._frame_wait is None and cam.cancelled == 0

    asyncio.run(main())


def test_no_frame_times_out() -> None:
    async def main() -> None:
        app, cam = _app(), _Frames()
        with pytest.raises(TimeoutError):
            await app._next_frame(cam, 0.05, wake_on_stop=True)
        assert cam.cancelled == 1  # the camera's read was cancelled, not left behind

    asyncio.run(main())


def test_a_stop_request_ends_the_wait_at_once() -> None:
    # a frame comes 2 s after the stop request: the wait must have ended before it
    async def main() -> None:
        app, cam = _app(), _Frames()
        loop = asyncio.get_running_loop()
        loop.call_later(0.05, app._stop.set)
        loop.call_later(2.0, lambda: cam.pending is not None and not cam.pending.done()
                        and cam.deliver("frame after the stop"))
        with pytest.raises(StopRequested):
            await app._next_frame(cam, 3600.0, wake_on_stop=True)
        assert cam.cancelled == 1
        with pytest.raises(StopRequested):  # already stopped: no wait at all
            await app._next_frame(cam, 30.0, wake_on_stop=True)

    asyncio.run(main())


def test_while_stopping_the_wait_is_not_cut_short() -> None:
    # after the stop (the exit's frames, wake_on_stop False) a frame is still waited for
    async def main() -> None:
        app, cam = _app(), _Frames()
        app._stop.set()
        loop = asyncio.get_running_loop()
        loop.call_later(0.02, app._stop.set)
        loop.call_later(0.05, lambda: cam.deliver("late frame"))
        assert await app._next_frame(cam, 30.0, wake_on_stop=False) == "late frame"

    asyncio.run(main())
