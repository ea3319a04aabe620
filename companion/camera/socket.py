"""The emulator's frame socket (docs/reference/wire.md, camera frames): record header, decoding and
:class:`FrameSocketSource`, a TCP client that resynchronises on a bad record."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import struct
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from fastcrc.crc32 import iso_hdlc as _crc32

from companion.camera.base import _CHANNELS, CameraError, CameraFrame, CameraSource, _Newest, _stop
from companion.camera.shm import (
    ANNOUNCE_MAGIC,
    NOTICE_MAGIC,
    REQUEST_SHM,
    Announcement,
    SharedFrames,
)

_log = logging.getLogger(__name__)


# docs/reference/wire.md, camera frames
FRAME_HEADER = struct.Struct("<4sBBHIQHHII")
FRAME_MAGIC = b"IBVF"
FRAME_VERSION = 1
ENCODINGS = {0: "mono8", 1: "bgr8", 2: "jpeg", 3: "png"}
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
DRAIN_ROUNDS = 256
"""Event-loop turns the consumer lets the socket be read before it takes a frame (each turn
reads a record's header or a part of its payload)."""

# ----------------------------------------------------------------------------------------------
# The emulator's frame socket (docs/reference/wire.md)


class BadRecord(CameraError):
    """A frame record violates docs/reference/wire.md (the connection must be resynchronised)."""


@dataclass(frozen=True)
class FrameHeader:
    """The 32-byte record header of docs/reference/wire.md."""

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

    def check(self, max_payload_bytes: int = MAX_PAYLOAD_BYTES,
              magic: bytes = FRAME_MAGIC) -> None:
        """Raise :class:`BadRecord` naming the first field that is not acceptable (``magic``:
        ``NOTICE_MAGIC`` for a shared-memory notice)."""
        if self.magic != magic:
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
    """One docs/reference/wire.md record for ``image`` (mono8 if 2-D, bgr8 if 3-D, or ``encoding`` =
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
        FRAME_MAGIC, FRAME_VERSION, code, 0, seq, t_us, w, h, len(payload), _crc32(payload)
    )
    return head + payload


def decode_payload(header: FrameHeader, payload: bytes | memoryview
                   ) -> tuple[npt.NDArray[np.uint8], str]:
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
    payload: bytes | memoryview | None  # read-only; None: a notice (the frame is in its slot)
    t_rx_ns: int


class _RecordProtocol(asyncio.BufferedProtocol):
    """Receives docs/reference/wire.md records straight into a buffer of their own (``recv_into``:
    one copy out of the kernel per byte).

    Why not ``asyncio.StreamReader.readexactly``: it copied a 1 MB frame about four times
    through its growing buffer, ~1.2 ms of CPU per frame on the event loop against ~0.1 ms here
    (measured on this 2-core machine), and in lockstep that time is in series with every step.
    ``on_record(header, payload)`` gets each record whose CRC matches (the payload read-only);
    :attr:`done` resolves with True on a bad record (:attr:`bad` says why; the caller
    resynchronises by reconnecting), or fails with the error when the connection ends
    (:class:`ConnectionError` at EOF)."""

    def __init__(self, on_record: Callable[[FrameHeader, memoryview | None], None],
                 max_payload_bytes: int,
                 on_announce: Callable[[Announcement, str], None] | None = None) -> None:
        self._on_record = on_record
        self._on_announce = on_announce
        self._announce: Announcement | None = None  # set while the segment's name is read
        self._announced_ok = False  # this connection's segment is mapped
        self._max_payload = max_payload_bytes
        self.done: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        self.bad: BadRecord | None = None
        self._head = bytearray(FRAME_HEADER.size)
        self._header: FrameHeader | None = None  # set while its payload is being read
        self._buf = memoryview(self._head)
        self._pos = 0

    def get_buffer(self, sizehint: int) -> memoryview:
        if self.done.done():  # finished: anything more is discarded until the socket closes
            return memoryview(bytearray(65536))
        return self._buf[self._pos:]

    def buffer_updated(self, nbytes: int) -> None:
        if self.done.done():
            return
        self._pos += nbytes
        if self._pos < len(self._buf):
            return
        try:
            if self._announce is not None:
                self._announced(self._announce, bytes(self._buf))
                return
            if self._header is None:
                if self._head[:4] != FRAME_MAGIC:
                    self._other_record()
                    return
                header = FrameHeader.unpack(bytes(self._head))
                header.check(self._max_payload)
                if header.payload_len > 0:  # read the payload next
                    self._read_next(header.payload_len)
                    self._header = header
                    return
                payload = memoryview(b"")
            else:
                header, payload = self._header, self._buf.toreadonly()
            if _crc32(payload) != header.crc32:
                raise BadRecord(f"CRC mismatch in frame {header.seq}")
        except BadRecord as exc:
            self.bad = exc
            self.done.set_result(True)
            return
        except CameraError as exc:  # a segment that cannot be mapped: no use reconnecting
            self.done.set_exception(exc)
            return
        self._header = None
        self._read_next(0)
        self._on_record(header, payload)

    def _read_next(self, payload_len: int) -> None:
        """Read ``payload_len`` bytes next (0: the next record's header)."""
        self._buf = memoryview(bytearray(payload_len)) if payload_len else memoryview(self._head)
        self._pos = 0

    def _other_record(self) -> None:
        """A header that is not a whole frame's: a shared-memory notice or announcement."""
        if self._on_announce is not None and self._head[:4] == NOTICE_MAGIC:
            if not self._announced_ok:
                raise BadRecord("a shared-memory notice before the segment's announcement")
            header = FrameHeader.unpack(bytes(self._head))
            header.check(self._max_payload, NOTICE_MAGIC)
            self._read_next(0)
            self._on_record(header, None)
        elif self._on_announce is not None and self._head[:4] == ANNOUNCE_MAGIC:
            try:
                ann = Announcement.unpack(bytes(self._head))
            except CameraError as exc:
                raise BadRecord(str(exc)) from exc
            self._announce = ann
            self._read_next(ann.name_len)
        else:
            raise BadRecord(f"bad magic {bytes(self._head[:4])!r}")

    def _announced(self, ann: Announcement, name: bytes) -> None:
        self._announce = None
        self._read_next(0)
        try:
            path = name.decode()
        except UnicodeDecodeError as exc:
            raise BadRecord(f"shared-memory segment name {name!r} is not UTF-8") from exc
        assert self._on_announce is not None
        self._on_announce(ann, path)
        self._announced_ok = True

    def needed_bytes(self) -> int:
        """Bytes still to read before the part being read (a header, or the payload the
        last header announced) is complete."""
        return len(self._buf) - self._pos

    def eof_received(self) -> bool:
        return False  # close: connection_lost follows

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.done.done():
            self.done.set_exception(exc if exc is not None
                                    else ConnectionError("connection closed by the emulator"))


class FrameSocketSource(CameraSource):
    """TCP client of the emulator's camera frames (docs/reference/wire.md).

    Reconnects with exponential backoff (``backoff_initial_s`` doubling up to
    ``backoff_max_s``; reset by a good frame). A record with a bad magic, version, encoding,
    size or CRC closes the connection and reconnects at once (``resyncs``). Records are
    decoded only when the consumer takes them (a dropped frame costs no decoding); JPEG/PNG
    decode in a worker thread.

    ``shared_memory`` (``?transport=shm``): ask the emulator for its frames through shared
    memory (same host only): the frames are copied out of the ring it announces when the
    consumer takes them; one overwritten or being written by then is dropped
    (``torn_frames``). A segment that cannot be mapped fails the source
    (:class:`CameraError` naming it). An emulator that does not offer shared memory keeps
    sending whole frames, which are taken as they come.
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
        read_ahead: bool = True,
        shared_memory: bool = False,
    ) -> None:
        super().__init__()
        if not 0 < port < 65536:
            raise CameraError(f"port: {port} is not a TCP port")
        if not 0 < backoff_initial_s <= backoff_max_s:
            raise CameraError("need 0 < backoff_initial_s <= backoff_max_s")
        self.host = host
        self.port = port
        self._queue_size = queue_size
        # skip to the newest record the kernel holds (_newest); False ("?frames=all"): every
        # record in turn, as the lockstep emulator expects (it waits for one answer per frame
        # it delivers, two when latency jitter delivers two in a step)
        self._read_ahead = read_ahead
        self._backoff = (backoff_initial_s, backoff_max_s)
        self._connect_timeout_s = connect_timeout_s
        self._max_payload = max_payload_bytes
        self._buffer: _Newest[_Record] | None = None
        self._task: asyncio.Task[None] | None = None
        # the connection being read (None between connections): how much it holds unread
        self._reading: tuple[_RecordProtocol, int] | None = None
        self._last_seq: int | None = None
        self._shared_memory = shared_memory
        self._shm: SharedFrames | None = None  # the announced ring, mapped
        self.connected = asyncio.Event()

    def __repr__(self) -> str:
        query = "?transport=shm" if self._shared_memory else ""
        return f"FrameSocketSource('tcp://{self.host}:{self.port}{query}')"

    async def _start(self) -> None:
        self._buffer = _Newest(self._queue_size)
        self._task = asyncio.create_task(self._run(), name=f"frames {self.host}:{self.port}")
        self._watch(self._task, self._buffer)

    async def _close(self) -> None:
        if self._task is not None:
            await _stop(self._task)
        if self._buffer is not None:
            self._buffer.close()
        self._unmap()

    def _unmap(self) -> None:
        if self._shm is not None:
            self._shm.close()
            self._shm = None

    def _announced(self, ann: Announcement, path: str) -> None:
        """The emulator's shared-memory segment (raises :class:`CameraError` if it cannot be
        mapped: the source fails)."""
        self._unmap()
        self._shm = SharedFrames(path, ann)
        _log.info("frame socket: frames through shared memory %s (%d slots)", path, ann.n_slots)

    def _slot_payload(self, rec: _Record) -> memoryview | None:
        """The payload of a notice's frame copied out of its slot (None: torn or lapped)."""
        h = rec.header
        if self._shm is None:  # a notice of a connection that is gone (and its segment)
            return None
        return self._shm.read(h.reserved, h.seq, h.t_us, h.payload_len, h.crc32)

    async def _next_frame(self) -> CameraFrame | None:
        assert self._buffer is not None
        while True:
            rec = await self._buffer.get()
            if rec is None:
                self._raise_if_failed()
                return None
            rec = await self._newest(rec)
            payload = rec.payload if rec.payload is not None else self._slot_payload(rec)
            if payload is None:
                self._count("torn_frames")
                _log.warning("frame %d dropped: its shared-memory slot was overwritten",
                             rec.header.seq)
                continue
            try:
                if rec.header.encoding in (2, 3):
                    image, enc = await asyncio.to_thread(decode_payload, rec.header, payload)
                else:
                    image, enc = decode_payload(rec.header, payload)
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

    async def _newest(self, rec: _Record) -> _Record:
        """The newest complete record, ``rec`` or one behind it that is already in the
        socket's receive buffer.

        A consumer that was busy (a step that overran, a companion short of CPU) finds the
        first record that completes after it waits, while newer ones sit unread in the kernel:
        taking that one would control from an old frame and leave the newer ones to age.
        So before a record is handed out (and decoded), the records the kernel already holds
        in full are read first; each replaces the one before it in the newest-frame buffer
        (counted as dropped), and only the newest is decoded. With ``queue_size`` > 1 the
        consumer asked for a queue of frames in order: ``rec`` as it is."""
        assert self._buffer is not None
        rounds = 0
        while (self._reading is not None and rounds < DRAIN_ROUNDS and self._queue_size == 1
               and self._read_ahead):
            proto, fd = self._reading
            pending = _unread_bytes(fd)
            if pending <= 0 or pending < proto.needed_bytes():
                break  # nothing more, or only part of a record that is still arriving
            if rounds == 0:
                self._buffer.put(rec)  # back in the buffer: a newer record replaces it
            await asyncio.sleep(0)  # one loop turn: the protocol reads what is there
            rounds += 1
        if rounds == 0:
            return rec
        newest = await self._buffer.get()
        return rec if newest is None else newest

    async def _run(self) -> None:
        delay = self._backoff[0]
        loop = asyncio.get_running_loop()
        while True:
            try:
                transport, proto = await asyncio.wait_for(
                    loop.create_connection(
                        lambda: _RecordProtocol(
                            self._received, self._max_payload,
                            self._announced if self._shared_memory else None),
                        self.host, self.port),
                    self._connect_timeout_s,
                )
            except (OSError, TimeoutError) as exc:
                self._count("connect_failures")
                _log.debug("frame socket %s:%d: connect failed: %s", self.host, self.port, exc)
                await asyncio.sleep(delay)
                delay = min(2 * delay, self._backoff[1])
                continue
            self._count("connects")
            if self._shared_memory:
                transport.write(REQUEST_SHM)
            sock = transport.get_extra_info("socket")
            self._reading = (proto, sock.fileno()) if sock is not None else None
            self.connected.set()
            _log.info("frame socket connected to %s:%d", self.host, self.port)
            resync = False
            try:
                resync = await self._read_records(proto)
            except (ConnectionError, OSError) as exc:
                self._count("disconnects")
                _log.warning("frame socket %s:%d lost: %s", self.host, self.port, exc)
            finally:
                self._reading = None
                self.connected.clear()
                transport.close()
            if resync:
                self._count("bad_records")
                self._count("resyncs")
                _log.warning("frame socket: %s: resynchronising", proto.bad)
                delay = self._backoff[0]
                continue  # reconnect at once: the stream restarts at a record boundary
            await asyncio.sleep(delay)
            delay = min(2 * delay, self._backoff[1])

    async def _read_records(self, proto: _RecordProtocol) -> bool:
        """Wait until the connection ends (raises) or a bad record (returns True); the
        protocol hands each good record to :meth:`_received` meanwhile."""
        return await proto.done

    def _received(self, header: FrameHeader, payload: memoryview | None) -> None:
        """A record with a good CRC, or a shared-memory notice (``payload`` None; called by
        :class:`_RecordProtocol`)."""
        assert self._buffer is not None
        t_rx_ns = time.monotonic_ns()
        self._count("frames_received")
        if self._last_seq is not None and header.seq > self._last_seq + 1:
            self._count("seq_gaps", header.seq - self._last_seq - 1)
        self._last_seq = header.seq
        if self._buffer.put(_Record(header, payload, t_rx_ns)):
            self._count("frames_dropped")


def _unread_bytes(fd: int) -> int:
    """Bytes received on socket ``fd`` and not read yet (FIONREAD; 0 when unknown)."""
    with contextlib.suppress(OSError):
        return int(struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0])
    return 0
