"""Camera frames on the wire (docs/reference/wire.md, "Camera frames"): the record format and the
TCP
server that streams them to any number of clients.

A record is a 32-byte little-endian header (``struct`` ``<4sBBHIQHHII``: magic ``b"IBVF"``,
version 1, encoding, reserved, seq, t_us, width, height, payload_len, crc32) followed by the
payload. A slow client gets the newest frame: each client has a one-frame slot; a frame that
replaces one not yet handed to the socket is dropped and counted (no unbounded buffering).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
from dataclasses import dataclass
from types import TracebackType

import cv2
import numpy as np
from fastcrc.crc32 import iso_hdlc as _crc32

from sim_bridge import LinkError, SimBridgeError
from sim_bridge.camera.shm import REQUEST, FrameRing, parse_request

__all__ = [
    "ENCODINGS",
    "HEADER",
    "MAGIC",
    "VERSION",
    "FrameError",
    "FrameHeader",
    "FrameServer",
    "decode_header",
    "decode_payload",
    "encode_frame",
    "encode_frame_parts",
    "read_frame",
]

log = logging.getLogger(__name__)

MAGIC = b"IBVF"
VERSION = 1
HEADER = struct.Struct("<4sBBHIQHHII")
ENCODINGS = {"mono8": 0, "bgr8": 1, "jpeg": 2, "png": 3}
_NAMES = {v: k for k, v in ENCODINGS.items()}
_MAX_PAYLOAD = 64 * 1024 * 1024


class FrameError(SimBridgeError):
    """A frame record that cannot be encoded or decoded (bad magic, version, size or CRC)."""


@dataclass(frozen=True)
class FrameHeader:
    """A decoded record header (docs/reference/wire.md). ``t_us``: capture time, emulator clock."""

    version: int
    encoding: int
    seq: int
    t_us: int
    width: int
    height: int
    payload_len: int
    crc32: int

    @property
    def encoding_name(self) -> str:
        return _NAMES[self.encoding]


def _encoding_code(encoding: str | int) -> int:
    if isinstance(encoding, str):
        if encoding not in ENCODINGS:
            raise FrameError(f"unknown encoding {encoding!r}: one of {', '.join(ENCODINGS)}")
        return ENCODINGS[encoding]
    if encoding not in _NAMES:
        raise FrameError(f"unknown encoding code {encoding}")
    return int(encoding)


def _payload(image: np.ndarray, code: int) -> bytes | memoryview:
    """The payload of ``image``: for the raw encodings a read-only view of its own memory (no
    copy when it is C-contiguous), else the compressed bytes."""
    if image.dtype != np.uint8:
        raise FrameError(f"image must be uint8, got {image.dtype}")
    if code == 0:
        if image.ndim != 2:
            raise FrameError(f"mono8 needs an (H, W) image, got shape {image.shape}")
        return np.ascontiguousarray(image).reshape(-1).data.toreadonly()
    if code == 1:
        if image.ndim != 3 or image.shape[2] != 3:
            raise FrameError(f"bgr8 needs an (H, W, 3) image, got shape {image.shape}")
        return np.ascontiguousarray(image).reshape(-1).data.toreadonly()
    ok, buf = cv2.imencode(".jpg" if code == 2 else ".png", image)
    if not ok:
        raise FrameError("cv2.imencode failed")
    return buf.tobytes()


def encode_payload(image: np.ndarray, encoding: str | int = "mono8") -> bytes:
    """The payload bytes of ``image`` (uint8 (H, W) for mono8, (H, W, 3) BGR for bgr8)."""
    payload = _payload(image, _encoding_code(encoding))
    return payload if isinstance(payload, bytes) else payload.tobytes()


def _check_fields(seq: int, t_us: int, image: np.ndarray) -> tuple[int, int]:
    """The image's height and width once the header fields fit (:class:`FrameError`)."""
    if not 0 <= seq <= 0xFFFFFFFF:
        raise FrameError(f"seq {seq} out of u32 range")
    if not 0 <= t_us <= 0xFFFFFFFFFFFFFFFF:
        raise FrameError(f"t_us {t_us} out of u64 range")
    h, w = image.shape[:2]
    if not (0 < w <= 0xFFFF and 0 < h <= 0xFFFF):
        raise FrameError(f"image size {w} x {h} does not fit the u16 header fields")
    return int(h), int(w)


def encode_frame_parts(seq: int, t_us: int, image: np.ndarray, encoding: str | int = "mono8"
                       ) -> tuple[bytes, bytes | memoryview]:
    """One record as (header, payload), not joined: for mono8/bgr8 the payload is a view of
    ``image``'s memory, so the image must not change until the record is written. The frame
    server sends the two parts as they are: copying a 1 MB frame into bytes and joining it to
    its header cost ~1 ms per frame (fresh 1 MB buffers fault their pages in), in series with
    every lockstep step."""
    h, w = _check_fields(seq, t_us, image)
    code = _encoding_code(encoding)
    payload = _payload(image, code)
    # fastcrc's CRC-32 (the same CRC-32/ISO-HDLC as zlib's, ~0.02 ms against zlib's ~0.23 ms on
    # a 1 MB frame; both ends compute one per frame, in series in lockstep; pymavlink needs it)
    header = HEADER.pack(
        MAGIC, VERSION, code, 0, seq, t_us, w, h, len(payload), _crc32(payload)
    )
    return header, payload


def encode_frame(seq: int, t_us: int, image: np.ndarray, encoding: str | int = "mono8") -> bytes:
    """One record (header + payload) for ``image`` with sequence number ``seq`` (u32) and
    capture time ``t_us`` (u64, microseconds since emulator boot)."""
    return b"".join(encode_frame_parts(seq, t_us, image, encoding))


def decode_header(data: bytes) -> FrameHeader:
    """Parse the first 32 bytes of a record; raises :class:`FrameError` on a bad magic,
    version, encoding or payload length (the client should then reconnect)."""
    if len(data) < HEADER.size:
        raise FrameError(f"header needs {HEADER.size} bytes, got {len(data)}")
    magic, version, enc, _res, seq, t_us, w, h, n, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise FrameError(f"bad magic {magic!r}")
    if version != VERSION:
        raise FrameError(f"unsupported version {version}")
    if enc not in _NAMES:
        raise FrameError(f"unknown encoding code {enc}")
    if n > _MAX_PAYLOAD or (enc in (0, 1) and n != w * h * (1 if enc == 0 else 3)):
        raise FrameError(f"payload length {n} inconsistent with {w} x {h} {_NAMES[enc]}")
    return FrameHeader(version, enc, seq, t_us, w, h, n, crc)


def decode_payload(header: FrameHeader, payload: bytes) -> np.ndarray:
    """The image of a record: checks the CRC (:class:`FrameError` on mismatch) and decodes."""
    if len(payload) != header.payload_len:
        raise FrameError(f"payload has {len(payload)} bytes, header says {header.payload_len}")
    if _crc32(payload) != header.crc32:
        raise FrameError(f"CRC mismatch in frame {header.seq}")
    if header.encoding == 0:
        return np.frombuffer(payload, np.uint8).reshape(header.height, header.width)
    if header.encoding == 1:
        return np.frombuffer(payload, np.uint8).reshape(header.height, header.width, 3)
    img = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.shape[:2] != (header.height, header.width):
        raise FrameError(f"frame {header.seq}: compressed payload does not decode")
    return np.asarray(img)


async def read_frame(reader: asyncio.StreamReader) -> tuple[FrameHeader, np.ndarray]:
    """Read one record from a stream (raises ``asyncio.IncompleteReadError`` at EOF and
    :class:`FrameError` on a bad record)."""
    header = decode_header(await reader.readexactly(HEADER.size))
    payload = await reader.readexactly(header.payload_len)
    return header, decode_payload(header, payload)


async def _until_eof(reader: asyncio.StreamReader, client: _Client) -> None:
    """Return when the peer closes its side. A client may send one request first (shared
    memory, docs/reference/wire.md); anything else it sends is ignored."""
    with contextlib.suppress(ConnectionError, OSError):
        head = b""
        while len(head) < REQUEST.size:
            data = await reader.read(REQUEST.size - len(head))
            if not data:
                return
            head += data
        client.wants_shm = parse_request(head) is not None
        if client.wants_shm:
            log.info("frame client %s asks for shared memory", client.peer)
        while await reader.read(4096):
            pass


class _Client:
    """One connected client: a one-record slot and a writer task that empties it."""

    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.peer = writer.get_extra_info("peername")
        self.slot: tuple[bytes | memoryview, ...] | None = None
        self.wants_shm = False  # it sent the shared-memory request
        self.announced = False  # it was sent the shared-memory segment's name
        self.wake = asyncio.Event()
        self.sent = 0
        self.dropped = 0
        self.task: asyncio.Task[object] | None = None

    def offer(self, record: tuple[bytes | memoryview, ...]) -> None:
        if self.slot is not None:
            self.dropped += 1
        self.slot = record
        self.wake.set()

    async def run(self) -> None:
        try:
            while True:
                await self.wake.wait()
                self.wake.clear()
                record, self.slot = self.slot, None
                if record is None:
                    continue
                for part in record:  # header, payload: written as they are (no join)
                    self.writer.write(part)
                if len(record) == 2 and record[0][:4] == b"IBVA":
                    self.announced = True
                await self.writer.drain()
                self.sent += 1
        except (ConnectionError, OSError) as e:
            log.info("frame client %s left: %s", self.peer, e)
        finally:
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()


class FrameServer:
    """TCP server streaming camera frames to any number of clients (docs/reference/wire.md).

    ``async with FrameServer("127.0.0.1", 0) as srv: await srv.publish(seq, t_us, image)``.
    ``port`` 0 picks a free port (read it from :attr:`port`); ``sock``: a listening socket to
    serve on instead (handed over by the process that chose the port: ``sim-bridge
    --frame-fd``). Counters: :attr:`published`, :attr:`sent` and :attr:`dropped` (over all
    clients, current and past), :attr:`n_clients`.
    """

    def __init__(self, host: str, port: int, encoding: str = "mono8",
                 sock: socket.socket | None = None) -> None:
        self.host = host
        self._listen_sock = sock
        self.requested_port = port
        self.encoding = encoding
        _encoding_code(encoding)
        self.port = port
        self.published = 0
        self._server: asyncio.Server | None = None
        self._clients: set[_Client] = set()
        self._closing = False
        self._gone_sent = 0
        self._gone_dropped = 0
        self._ring: FrameRing | None = None
        self._ring_failed = False

    async def __aenter__(self) -> FrameServer:
        try:
            if self._listen_sock is not None:
                self._server = await asyncio.start_server(self._on_client,
                                                          sock=self._listen_sock)
            else:
                self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        except OSError as e:
            raise LinkError(f"camera frames: cannot listen on {self.host}:{self.port}: {e}") from e
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("camera frames on tcp %s:%d", self.host, self.port)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def close(self) -> None:
        self._closing = True
        if self._ring is not None:
            self._ring.close()
        if self._server is not None:
            self._server.close()
        for c in list(self._clients):
            if c.task is not None:
                c.task.cancel()
        for c in list(self._clients):
            if c.task is not None:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await c.task
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = _Client(writer)
        log.info("frame client %s connected", client.peer)
        self._clients.add(client)
        client.task = asyncio.current_task()
        run = asyncio.ensure_future(client.run())
        eof = asyncio.ensure_future(_until_eof(reader, client))
        try:
            # The client leaves when it closes its side (EOF) or when writing to it fails.
            await asyncio.wait({run, eof}, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            # Shutting down: end normally. Python 3.11's start_server callback calls
            # task.exception() on the handler and logs the CancelledError as an error.
            if not self._closing:
                raise
        finally:
            for task in (run, eof):
                task.cancel()
            await asyncio.gather(run, eof, return_exceptions=True)
            self._clients.discard(client)
            self._gone_sent += client.sent
            self._gone_dropped += client.dropped
            log.info(
                "frame client %s gone (%d sent, %d dropped)",
                client.peer,
                client.sent,
                client.dropped,
            )

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    @property
    def sent(self) -> int:
        return self._gone_sent + sum(c.sent for c in self._clients)

    @property
    def dropped(self) -> int:
        return self._gone_dropped + sum(c.dropped for c in self._clients)

    async def publish(self, seq: int, t_us: int, image: np.ndarray) -> None:
        """Encode once and offer the record to every connected client (never blocks on
        them): the whole record over TCP, or to a client that asked for shared memory the
        frame written once into the ring and a notice naming its slot."""
        if self._clients:
            record: tuple[bytes | memoryview, ...] | None = None
            notice: bytes | None = None  # b"": this frame not through the ring
            for c in list(self._clients):
                if c.wants_shm and notice is None:
                    notice = await self._ring_notice(seq, t_us, image)
                if c.wants_shm and notice:
                    c.offer((notice,) if c.announced or self._ring is None
                            else (self._ring.announcement, notice))
                    continue
                if record is None:
                    record = await self._encode(seq, t_us, image)
                c.offer(record)
        self.published += 1
        await asyncio.sleep(0)

    async def _encode(self, seq: int, t_us: int, image: np.ndarray
                      ) -> tuple[bytes, bytes | memoryview]:
        if self.encoding in ("mono8", "bgr8"):
            return encode_frame_parts(seq, t_us, image, self.encoding)
        # compression takes milliseconds: keep the event loop free
        return await asyncio.to_thread(encode_frame_parts, seq, t_us, image, self.encoding)

    async def _ring_notice(self, seq: int, t_us: int, image: np.ndarray) -> bytes:
        """The frame written into the shared-memory ring (created on first use): its
        notice, or b"" when the ring cannot take it (the client then gets the whole
        record over TCP, as a client that did not ask)."""
        if self._ring_failed:
            return b""
        code = _encoding_code(self.encoding)
        h, w = _check_fields(seq, t_us, image)
        payload = _payload(image, code) if code in (0, 1) else \
            await asyncio.to_thread(_payload, image, code)
        if self._ring is None:
            try:  # a compressed frame's size varies: room for a raw one and more
                room = len(payload) if code in (0, 1) else image.nbytes + 65536
                self._ring = FrameRing(room, tag=str(self.port))
            except LinkError as e:
                self._ring_failed = True
                log.warning("camera frames: no shared memory, the whole frames over TCP: %s", e)
                return b""
        if len(payload) > self._ring.capacity:  # this frame whole over TCP
            log.warning("camera frame %d (%d bytes) does not fit a shared-memory slot", seq,
                        len(payload))
            return b""
        return self._ring.write(HEADER, (code, seq, t_us, w, h), payload)
