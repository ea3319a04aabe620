"""Camera sources' common interface: :class:`CameraFrame`, :class:`CameraSource` (an async
iterator with a bounded newest-frame buffer that drops the oldest and counts it)."""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
from collections import deque
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Generic, Self, TypeVar

import numpy as np
import numpy.typing as npt

from companion import CompanionError

_log = logging.getLogger(__name__)



#: channels per raw pixel encoding
_CHANNELS = {"mono8": 1, "bgr8": 3}


class CameraError(CompanionError):
    """A camera source cannot be opened or was misconfigured (bad URL, missing file)."""


@dataclass(frozen=True)
class CameraFrame:
    """One image and its times.

    ``seq``: the source's frame counter (+1 per frame; gaps = frames dropped upstream or
    here). ``t_us``: capture time on the *source's* clock (emulator boot time for the frame
    socket, stream position or receipt for ``cv2.VideoCapture``), microseconds.
    ``t_rx_ns``: local ``time.monotonic_ns()`` when the frame was received in full.
    ``image``: (H, W) uint8 for ``"mono8"``, (H, W, 3) uint8 BGR for ``"bgr8"`` (read-only).
    ``encoding``: the pixel format of ``image``; ``wire_encoding``: how it arrived
    (``mono8``/``bgr8``/``jpeg``/``png``/``capture``).
    """

    seq: int
    t_us: int
    t_rx_ns: int
    image: npt.NDArray[np.uint8] = field(repr=False)
    encoding: str
    wire_encoding: str = ""

    def __post_init__(self) -> None:
        if self.encoding not in _CHANNELS:
            raise CameraError(f"CameraFrame.encoding: {self.encoding!r} is not mono8 or bgr8")
        want = 2 if self.encoding == "mono8" else 3
        if self.image.dtype != np.uint8 or self.image.ndim != want:
            raise CameraError(f"CameraFrame.image: {self.image.shape} does not fit {self.encoding}")

    @property
    def width_px(self) -> int:
        return int(self.image.shape[1])

    @property
    def height_px(self) -> int:
        return int(self.image.shape[0])


@dataclass(frozen=True)
class SourceStats:
    """Counters of a source since it was opened (a snapshot)."""

    frames_received: int = 0  # complete, valid records / captured frames
    frames_delivered: int = 0  # handed to the consumer
    frames_dropped: int = 0  # dropped here because the consumer was slow
    seq_gaps: int = 0  # frames missing upstream (seq jumps)
    bad_records: int = 0  # bad magic / version / encoding / size / CRC (each -> resync)
    resyncs: int = 0  # reconnects caused by a bad record
    connects: int = 0  # successful connections (1 = never reconnected)
    connect_failures: int = 0
    disconnects: int = 0  # connection lost (peer closed / reset)
    decode_errors: int = 0  # payloads that did not decode (jpeg/png, capture read)
    torn_frames: int = 0  # shared-memory frames overwritten before they were read (dropped)


_T = TypeVar("_T")


class _Newest(Generic[_T]):
    """Bounded buffer for one consumer: ``put`` drops the oldest when full (returns True when
    it did), ``get`` waits; ``close`` wakes the consumer with ``None``."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise CameraError("queue_size: must be >= 1")
        self._items: deque[_T] = deque()
        self._size = size
        self._event = asyncio.Event()
        self._closed = False

    def put(self, item: _T) -> bool:
        dropped = False
        if len(self._items) >= self._size:
            self._items.popleft()
            dropped = True
        self._items.append(item)
        self._event.set()
        return dropped

    async def get(self) -> _T | None:
        while not self._items:
            if self._closed:
                return None
            self._event.clear()
            await self._event.wait()
        return self._items.popleft()

    def close(self) -> None:
        self._closed = True
        self._event.set()


class CameraSource(abc.ABC):
    """Async context manager and async iterator of :class:`CameraFrame`.

    ``async with source: async for frame in source: ...``; iteration ends when the source
    ends (end of a file) or is closed. ``stats`` gives the counters.
    """

    def __init__(self) -> None:
        self._counters: dict[str, int] = dict.fromkeys(SourceStats.__dataclass_fields__, 0)
        self._started = False
        self._closed = False
        self._error: BaseException | None = None

    def _watch(self, task: asyncio.Task[None], buffer: _Newest[Any]) -> None:
        """If the background ``task`` dies, wake the consumer and make it raise."""

        def done(t: asyncio.Task[None]) -> None:
            if not t.cancelled() and t.exception() is not None:
                self._error = t.exception()
                _log.error("%r: background task failed: %r", self, self._error)
                buffer.close()

        task.add_done_callback(done)

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise CameraError(f"{self!r} failed: {self._error!r}") from self._error

    @property
    def stats(self) -> SourceStats:
        return SourceStats(**self._counters)

    def _count(self, name: str, n: int = 1) -> None:
        self._counters[name] += n

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> CameraFrame:
        if not self._started:
            await self.start()
        frame = await self._next_frame()
        if frame is None:
            raise StopAsyncIteration
        self._count("frames_delivered")
        return frame

    async def start(self) -> None:
        if self._started:
            return
        if self._closed:
            raise CameraError("source already closed")
        self._started = True
        await self._start()

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        await self._close()

    @abc.abstractmethod
    async def _start(self) -> None: ...

    @abc.abstractmethod
    async def _close(self) -> None: ...

    @abc.abstractmethod
    async def _next_frame(self) -> CameraFrame | None: ...


async def _stop(task: asyncio.Task[None]) -> None:
    """Cancel and reap a background task; a failure it already reported is not raised again."""
    if not task.done():
        task.cancel()
    # a failure was already logged and surfaced by CameraSource._watch
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await task

