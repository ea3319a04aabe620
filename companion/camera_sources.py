"""Camera sources: one async interface over the emulator's frame socket, cameras and video.

``async with open_camera(url) as cam: async for frame in cam: ...`` yields frozen
:class:`CameraFrame` values. A consumer that falls behind gets the newest frame: every source
keeps a small bounded buffer that drops the oldest frame and counts it (style habit 6).

URLs (:func:`open_camera`):

- ``tcp://127.0.0.1:5700``: the emulator's frame socket (docs/wire.md), :class:`FrameSocketSource`
- ``0``, ``/dev/video0``: a local camera device, ``rtsp://...``, ``http(s)://...``, ``udp://...``:
  a live stream; a file path (or ``file://path``): a video file (read at the consumer's pace,
  nothing dropped). All through ``cv2.VideoCapture``: :class:`VideoCaptureSource`.
- ``*.mcap`` / ``mcap://``: recorded frames (the replay source; not implemented yet).
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import re
import struct
import time
import zlib
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Generic, Self, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from companion import CompanionError

_log = logging.getLogger(__name__)

# docs/wire.md, camera frames
FRAME_HEADER = struct.Struct("<4sBBHIQHHII")
FRAME_MAGIC = b"IBVF"
FRAME_VERSION = 1
ENCODINGS = {0: "mono8", 1: "bgr8", 2: "jpeg", 3: "png"}
_CHANNELS = {"mono8": 1, "bgr8": 3}
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024


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


# ----------------------------------------------------------------------------------------------
# The emulator's frame socket (docs/wire.md)


class BadRecord(CameraError):
    """A frame record violates docs/wire.md (the connection must be resynchronised)."""


@dataclass(frozen=True)
class FrameHeader:
    """The 32-byte record header of docs/wire.md."""

    magic: bytes
    version: int
    encoding: int
    reserved: int
    seq: int
    t_us: int
    width_px: int
    height_px: int
    payload_len: int
    crc32: int

    @classmethod
    def unpack(cls, data: bytes) -> FrameHeader:
        return cls(*FRAME_HEADER.unpack(data))

    def check(self, max_payload_bytes: int = MAX_PAYLOAD_BYTES) -> None:
        """Raise :class:`BadRecord` naming the first field that is not acceptable."""
        if self.magic != FRAME_MAGIC:
            raise BadRecord(f"bad magic {self.magic!r}")
        if self.version != FRAME_VERSION:
            raise BadRecord(f"unsupported version {self.version}")
        name = ENCODINGS.get(self.encoding)
        if name is None:
            raise BadRecord(f"unknown encoding {self.encoding}")
        if self.width_px == 0 or self.height_px == 0:
            raise BadRecord(f"empty image {self.width_px}x{self.height_px}")
        if self.payload_len > max_payload_bytes:
            raise BadRecord(f"payload_len {self.payload_len} > {max_payload_bytes}")
        if name in _CHANNELS:
            want = self.width_px * self.height_px * _CHANNELS[name]
            if self.payload_len != want:
                raise BadRecord(f"payload_len {self.payload_len} != {want} for raw {name}")


def pack_frame(
    seq: int, t_us: int, image: npt.NDArray[np.uint8], encoding: str = "", payload: bytes = b""
) -> bytes:
    """One docs/wire.md record for ``image`` (mono8 if 2-D, bgr8 if 3-D, or ``encoding`` =
    ``"jpeg"``/``"png"`` to compress; ``payload`` overrides the bytes sent). For tests,
    tools and recorders that re-serve frames."""
    h, w = image.shape[:2]
    if not encoding:
        encoding = "mono8" if image.ndim == 2 else "bgr8"
    code = {v: k for k, v in ENCODINGS.items()}[encoding]
    if not payload:
        if encoding in _CHANNELS:
            payload = np.ascontiguousarray(image).tobytes()
        else:
            ok, buf = cv2.imencode("." + ("jpg" if encoding == "jpeg" else "png"), image)
            if not ok:
                raise CameraError(f"cannot encode image as {encoding}")
            payload = buf.tobytes()
    head = FRAME_HEADER.pack(
        FRAME_MAGIC, FRAME_VERSION, code, 0, seq, t_us, w, h, len(payload), zlib.crc32(payload)
    )
    return head + payload


def decode_payload(header: FrameHeader, payload: bytes) -> tuple[npt.NDArray[np.uint8], str]:
    """Image and pixel format of a checked record's payload (raises :class:`CameraError`)."""
    name = ENCODINGS[header.encoding]
    h, w = header.height_px, header.width_px
    if name == "mono8":
        return np.frombuffer(payload, np.uint8).reshape(h, w), "mono8"
    if name == "bgr8":
        return np.frombuffer(payload, np.uint8).reshape(h, w, 3), "bgr8"
    img = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CameraError(f"{name} payload does not decode")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.dtype != np.uint8:
        raise CameraError(f"{name} payload decodes to {img.dtype}, expected 8-bit")
    if img.shape[:2] != (h, w):
        raise CameraError(f"{name} payload is {img.shape[1]}x{img.shape[0]}, header {w}x{h}")
    out = np.asarray(img, dtype=np.uint8)
    out.setflags(write=False)
    return out, "mono8" if out.ndim == 2 else "bgr8"


@dataclass(frozen=True)
class _Record:
    header: FrameHeader
    payload: bytes
    t_rx_ns: int


class FrameSocketSource(CameraSource):
    """TCP client of the emulator's camera frames (docs/wire.md).

    Reconnects with exponential backoff (``backoff_initial_s`` doubling up to
    ``backoff_max_s``; reset by a good frame). A record with a bad magic, version, encoding,
    size or CRC closes the connection and reconnects at once (``resyncs``). Records are
    decoded only when the consumer takes them (a dropped frame costs no decoding); JPEG/PNG
    decode in a worker thread.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        queue_size: int = 1,
        backoff_initial_s: float = 0.05,
        backoff_max_s: float = 2.0,
        connect_timeout_s: float = 2.0,
        max_payload_bytes: int = MAX_PAYLOAD_BYTES,
    ) -> None:
        super().__init__()
        if not 0 < port < 65536:
            raise CameraError(f"port: {port} is not a TCP port")
        if not 0 < backoff_initial_s <= backoff_max_s:
            raise CameraError("need 0 < backoff_initial_s <= backoff_max_s")
        self.host = host
        self.port = port
        self._queue_size = queue_size
        self._backoff = (backoff_initial_s, backoff_max_s)
        self._connect_timeout_s = connect_timeout_s
        self._max_payload = max_payload_bytes
        self._buffer: _Newest[_Record] | None = None
        self._task: asyncio.Task[None] | None = None
        self._last_seq: int | None = None
        self.connected = asyncio.Event()

    def __repr__(self) -> str:
        return f"FrameSocketSource('tcp://{self.host}:{self.port}')"

    async def _start(self) -> None:
        self._buffer = _Newest(self._queue_size)
        self._task = asyncio.create_task(self._run(), name=f"frames {self.host}:{self.port}")
        self._watch(self._task, self._buffer)

    async def _close(self) -> None:
        if self._task is not None:
            await _stop(self._task)
        if self._buffer is not None:
            self._buffer.close()

    async def _next_frame(self) -> CameraFrame | None:
        assert self._buffer is not None
        while True:
            rec = await self._buffer.get()
            if rec is None:
                self._raise_if_failed()
                return None
            try:
                if rec.header.encoding in (2, 3):
                    image, enc = await asyncio.to_thread(decode_payload, rec.header, rec.payload)
                else:
                    image, enc = decode_payload(rec.header, rec.payload)
            except CameraError as exc:
                self._count("decode_errors")
                _log.warning("frame %d dropped: %s", rec.header.seq, exc)
                continue
            return CameraFrame(
                rec.header.seq,
                rec.header.t_us,
                rec.t_rx_ns,
                image,
                enc,
                ENCODINGS[rec.header.encoding],
            )

    async def _run(self) -> None:
        delay = self._backoff[0]
        while True:
            try:
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(self.host, self.port), self._connect_timeout_s
                )
            except (OSError, TimeoutError) as exc:
                self._count("connect_failures")
                _log.debug("frame socket %s:%d: connect failed: %s", self.host, self.port, exc)
                await asyncio.sleep(delay)
                delay = min(2 * delay, self._backoff[1])
                continue
            self._count("connects")
            self.connected.set()
            _log.info("frame socket connected to %s:%d", self.host, self.port)
            resync = False
            try:
                resync = await self._read_records(reader)
            except (asyncio.IncompleteReadError, ConnectionError, OSError) as exc:
                self._count("disconnects")
                _log.warning("frame socket %s:%d lost: %s", self.host, self.port, exc)
            finally:
                self.connected.clear()
                writer.close()
                with contextlib.suppress(OSError, ConnectionError):
                    await writer.wait_closed()
            if resync:
                delay = self._backoff[0]
                continue  # reconnect at once: the stream restarts at a record boundary
            await asyncio.sleep(delay)
            delay = min(2 * delay, self._backoff[1])

    async def _read_records(self, reader: asyncio.StreamReader) -> bool:
        """Read records until the connection ends (raises) or a bad record (returns True)."""
        assert self._buffer is not None
        while True:
            raw = await reader.readexactly(FRAME_HEADER.size)
            header = FrameHeader.unpack(raw)
            try:
                header.check(self._max_payload)
                payload = await reader.readexactly(header.payload_len)
                if zlib.crc32(payload) != header.crc32:
                    raise BadRecord(f"CRC mismatch in frame {header.seq}")
            except BadRecord as exc:
                self._count("bad_records")
                self._count("resyncs")
                _log.warning("frame socket: %s: resynchronising", exc)
                return True
            t_rx_ns = time.monotonic_ns()
            self._count("frames_received")
            if self._last_seq is not None and header.seq > self._last_seq + 1:
                self._count("seq_gaps", header.seq - self._last_seq - 1)
            self._last_seq = header.seq
            if self._buffer.put(_Record(header, payload, t_rx_ns)):
                self._count("frames_dropped")


# ----------------------------------------------------------------------------------------------
# cv2.VideoCapture (devices, files, network streams)


class VideoCaptureSource(CameraSource):
    """Frames from ``cv2.VideoCapture(source)``: a device index, a device path, a file or a
    stream URL. Every OpenCV call runs on one dedicated worker thread (VideoCapture is not
    thread-safe and its calls block).

    ``live``: a live source is grabbed continuously and the consumer gets the newest frame
    (the driver's own queue would otherwise hand out stale frames); a file is read at the
    consumer's pace, nothing dropped. ``None`` = live unless ``source`` is a file path.
    ``t_us``: the stream position (``CAP_PROP_POS_MSEC``) for files; for live sources the
    receipt time since opening (cameras' positions are not reliable across backends).
    ``gray``: convert to mono8 on the worker thread.
    """

    def __init__(
        self,
        source: str | int,
        *,
        live: bool | None = None,
        queue_size: int = 1,
        api_preference: int = cv2.CAP_ANY,
        gray: bool = False,
        reopen_after_failures: int = 10,
        reopen_backoff_s: float = 1.0,
    ) -> None:
        super().__init__()
        self.source = source
        is_file = isinstance(source, str) and Path(source).is_file()
        self.live = (not is_file) if live is None else live
        self._queue_size = queue_size
        self._api = api_preference
        self._gray = gray
        self._reopen_after = reopen_after_failures
        self._reopen_backoff_s = reopen_backoff_s
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="videocapture")
        self._cap: cv2.VideoCapture | None = None
        self._buffer: _Newest[CameraFrame] | None = None
        self._task: asyncio.Task[None] | None = None
        self._seq = 0
        self._t0_ns = 0
        self._eof = False

    def __repr__(self) -> str:
        return f"VideoCaptureSource({self.source!r}, live={self.live})"

    async def _call(self, fn: Callable[..., _T], *args: Any) -> _T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.source, self._api)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"cv2.VideoCapture cannot open {self.source!r}")
        return cap

    async def _start(self) -> None:
        try:
            self._cap = await self._call(self._open)
        except BaseException:
            self._pool.shutdown(wait=False)
            raise
        self._t0_ns = time.monotonic_ns()
        if self.live:
            self._buffer = _Newest(self._queue_size)
            self._task = asyncio.create_task(self._grab_loop(), name=f"capture {self.source!r}")
            self._watch(self._task, self._buffer)

    async def _close(self) -> None:
        if self._task is not None:
            await _stop(self._task)
        if self._buffer is not None:
            self._buffer.close()
        if self._cap is not None:
            cap = self._cap
            self._cap = None
            await self._call(cap.release)
        self._pool.shutdown(wait=False)

    def _read(self) -> tuple[npt.NDArray[np.uint8], float, int] | None:
        """On the worker thread: one frame, its stream position (ms) and receipt time."""
        cap = self._cap
        if cap is None:
            return None
        ok, img = cap.read()
        t_rx_ns = time.monotonic_ns()
        if not ok or img is None:
            return None
        pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img)
        if self._gray and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        elif img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        out = np.asarray(img, dtype=np.uint8)
        out.setflags(write=False)
        return out, pos_ms, t_rx_ns

    def _frame(self, got: tuple[npt.NDArray[np.uint8], float, int]) -> CameraFrame:
        img, pos_ms, t_rx_ns = got
        t_us = (t_rx_ns - self._t0_ns) // 1000 if self.live else round(pos_ms * 1000.0)
        frame = CameraFrame(
            self._seq, t_us, t_rx_ns, img, "mono8" if img.ndim == 2 else "bgr8", "capture"
        )
        self._seq += 1
        self._count("frames_received")
        return frame

    async def _next_frame(self) -> CameraFrame | None:
        if self.live:
            assert self._buffer is not None
            frame = await self._buffer.get()
            if frame is None:
                self._raise_if_failed()
            return frame
        if self._eof:
            return None
        got = await self._call(self._read)
        if got is None:
            self._eof = True
            return None
        return self._frame(got)

    async def _grab_loop(self) -> None:
        assert self._buffer is not None
        failures = 0
        while True:
            got = await self._call(self._read)
            if got is None:
                failures += 1
                self._count("decode_errors")
                if failures >= self._reopen_after:
                    _log.warning("%r: %d failed reads, reopening", self, failures)
                    await self._reopen()
                    failures = 0
                else:
                    await asyncio.sleep(0.01)
                continue
            failures = 0
            if self._buffer.put(self._frame(got)):
                self._count("frames_dropped")

    async def _reopen(self) -> None:
        old, self._cap = self._cap, None
        if old is not None:
            await self._call(old.release)
        self._count("disconnects")
        while True:
            await asyncio.sleep(self._reopen_backoff_s)
            try:
                self._cap = await self._call(self._open)
            except CameraError as exc:
                self._count("connect_failures")
                _log.warning("%s", exc)
                continue
            self._count("connects")
            return


# ----------------------------------------------------------------------------------------------
# URL dispatch

_TCP = re.compile(r"^tcp://(?P<host>\[[^\]]+\]|[^:/]+):(?P<port>\d+)/?$")
_STREAM_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "rtp://")


def open_camera(url: str, **kwargs: Any) -> CameraSource:
    """The source ``url`` names (see the module docstring). Nothing is opened until the
    source is entered (``async with``) or iterated; ``kwargs`` go to the source's
    constructor. Raises :class:`CameraError` for an unusable URL."""
    url = url.strip()
    if not url:
        raise CameraError("camera url: empty")
    if url.startswith("tcp://"):
        m = _TCP.match(url)
        if m is None:
            raise CameraError(f"camera url {url!r}: expected tcp://host:port")
        return FrameSocketSource(m["host"].strip("[]"), int(m["port"]), **kwargs)
    if url.startswith("mcap://") or url.endswith(".mcap"):
        return _open_mcap(url, **kwargs)
    if url.isdigit():
        return VideoCaptureSource(int(url), live=True, **kwargs)
    if url.startswith("/dev/"):
        return VideoCaptureSource(url, live=True, **kwargs)
    if url.startswith(_STREAM_SCHEMES):
        return VideoCaptureSource(url, live=True, **kwargs)
    path = url.removeprefix("file://")
    if "://" in path:
        raise CameraError(f"camera url {url!r}: unknown scheme")
    if not Path(path).expanduser().is_file():
        raise CameraError(f"camera url {url!r}: no such file")
    return VideoCaptureSource(str(Path(path).expanduser()), live=False, **kwargs)


def _open_mcap(url: str, **kwargs: Any) -> CameraSource:
    path = url.removeprefix("mcap://")
    if not Path(path).expanduser().is_file():
        raise CameraError(f"camera url {url!r}: no such file")
    return McapSource(Path(path).expanduser(), **kwargs)


class McapSource(CameraSource):
    """Frames recorded in a companion log (``/camera/image``: foxglove.CompressedImage or
    RawImage), in log order, with their original capture time (``t_us`` from the image
    stamp) and receipt time (``t_rx_ns`` = the log time). ``pace``: deliver at the recorded
    rate instead of as fast as the consumer reads. A log cut short ends where its recovered
    part ends."""

    def __init__(self, path: Path, topic: str = "/camera/image", pace: bool = False) -> None:
        super().__init__()
        self.path = Path(path)
        self.topic = topic
        self._pace = pace
        self._reader: Any = None
        self._it: Any = None
        self._seq = 0
        self._t0: tuple[int, float] | None = None

    def __repr__(self) -> str:
        return f"McapSource({str(self.path)!r})"

    async def _start(self) -> None:
        from companion.log_reader import LogReader  # the reader is only needed here

        try:
            self._reader = LogReader(self.path)
        except CompanionError as exc:
            raise CameraError(f"{self!r}: {exc}") from exc
        self._it = self._reader.messages(topics=[self.topic])

    async def _close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    async def _next_frame(self) -> CameraFrame | None:
        while True:
            m = await asyncio.get_running_loop().run_in_executor(None, next, self._it, None)
            if m is None:
                return None
            if m.image is None:
                self._count("decode_errors")
                continue
            break
        self._count("frames_received")
        stamp = (m.data or {}).get("timestamp") or {}
        t_ns = int(stamp.get("sec", 0)) * 1_000_000_000 + int(stamp.get("nsec", 0))
        if self._pace:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = (m.log_time_ns, now)
            due = self._t0[1] + (m.log_time_ns - self._t0[0]) * 1e-9
            if due > now:
                await asyncio.sleep(due - now)
        img = np.ascontiguousarray(m.image)
        img.setflags(write=False)
        self._seq += 1
        enc = "mono8" if img.ndim == 2 else "bgr8"
        return CameraFrame(self._seq, t_ns // 1000, m.log_time_ns, img, enc, "mcap")


__all__ = [
    "FRAME_HEADER",
    "BadRecord",
    "CameraError",
    "CameraFrame",
    "CameraSource",
    "FrameHeader",
    "FrameSocketSource",
    "SourceStats",
    "VideoCaptureSource",
    "decode_payload",
    "open_camera",
    "pack_frame",
]
