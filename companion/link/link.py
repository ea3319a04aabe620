"""A robust MAVLink 2 link for the companion: asyncio transport, hostile-input receive path.

Why not ``mavutil``: its UDP connections feed every datagram into ONE shared parser, so a single
truncated datagram poisons the following good frames (docs/reference/pitfalls.md, pymavlink).
Here a datagram that is one MAVLink 2 frame is read at its header offsets
(:mod:`companion.link.wire`), any other by a robust parser reset for it; streams (TCP, serial)
keep one robust parser. pymavlink is the codec (``pymavlink.dialects.v20.common``).

The receive path (:mod:`companion.link.receive`) decides, frame by frame and in order, what is
accepted; each rejection increments ``counters[reason]``. Accepted frames become
:class:`Received` objects in a bounded queue that drops the oldest (``queue_overflow``); iterate
with ``async for rx in link``. The sockets and the serial device are
:mod:`companion.link.transport`'s.

Signing: the key file holds the 32-byte secret either as exactly 32 raw bytes or as 64 hex
characters (surrounding whitespace ignored); incoming signatures are verified by the receive
path (not by pymavlink: see :mod:`companion.link.receive`).
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.commands import LinkCommands
from companion.link.endpoints import parse_connection_string
from companion.link.errors import LinkError
from companion.link.filters import AllowRule, ValueLimits, default_allow_rules
from companion.link.guard import GuardParams, SourceGuard
from companion.link.messages import Received, Sent
from companion.link.receive import ReceivePath, new_parser, reset_parser
from companion.link.signing import SignatureVerifier, load_signing_key, signing_timestamp_now
from companion.link.transport import (
    StreamProtocol,
    bound_udp_socket,
    connected_udp_socket,
    open_serial,
)

log = logging.getLogger(__name__)


_CLOSED = object()


class MavlinkLink(LinkCommands):
    """An async MAVLink 2 link: ``async with MavlinkLink(url, ...) as link: async for rx in link``.

    Parameters
    ----------
    url: connection string (see :func:`parse_connection_string`).
    source_system, source_component: our ids in every frame we send.
    target_system, target_component: the autopilot (targets of commands and setpoints; in
        ``udpin`` mode the reply address is learned from its accepted frames).
    allow: whitelist rules; default: any message from the target system/component.
    limits: value plausibility bounds.
    signing_key: 32-byte key enabling MAVLink 2 signing (outgoing signed, incoming verified,
        unsigned incoming rejected unless its msgid is in ``allow_unsigned_msgids``).
    queue_size: receive queue bound; the oldest frame is dropped when full.
    clock_ns: the clock stamping ``t_rx_ns`` / ``t_tx_ns`` (default ``time.monotonic_ns``).
    on_rx / on_tx / on_reject: observers called in the event loop thread for every accepted
        frame, every sent frame, and rejected frames ``(reason, raw_bytes, t_ns)`` (at most
        ``guard.reject_log_per_s`` per second; every rejection is counted).
    guard: UDP receive guard (source pinning, allowed sources, work bounds; see
        :mod:`companion.link.guard`); default :class:`GuardParams` ().
    queue_frames: also put accepted frames on the receive queue (``async for``, ``recv``).
        False: they reach ``on_rx`` only, and an ``async for`` just waits for the close.
        :meth:`from_config` sets it False when ``on_rx`` is given.
    """

    def __init__(
        self,
        url: str,
        *,
        source_system: int,
        source_component: int,
        target_system: int,
        target_component: int,
        allow: Sequence[AllowRule] | None = None,
        limits: ValueLimits | None = None,
        signing_key: bytes | None = None,
        signing_link_id: int = 0,
        allow_unsigned_msgids: Iterable[int] = (),
        queue_size: int = 1024,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        on_rx: Callable[[Received], None] | None = None,
        on_tx: Callable[[Sent], None] | None = None,
        on_reject: Callable[[str, bytes, int], None] | None = None,
        guard: GuardParams | None = None,
        queue_frames: bool = True,
    ) -> None:
        self.endpoint = parse_connection_string(url)
        for nm, v, lo in (
            ("source_system", source_system, 1),
            ("source_component", source_component, 1),
            ("target_system", target_system, 1),
            ("target_component", target_component, 0),
        ):
            if not lo <= v <= 255:
                raise LinkError(f"{nm} = {v} not in {lo}..255")
        if queue_size < 1:
            raise LinkError("queue_size must be >= 1")
        self.source_system = source_system
        self.source_component = source_component
        self.target_system = target_system
        self.target_component = target_component
        rules = (
            allow if allow is not None else (AllowRule(target_system, target_component or None),)
        )
        self.guard_params = guard or GuardParams()
        identities: list[tuple[int, int | None, str | None]] = [
            (target_system, target_component or None, "HEARTBEAT")]
        for r in rules:
            if r.sysid != target_system and all(r.sysid != i[0] for i in identities):
                identities.append((r.sysid, r.compid, None))
        self.guard = SourceGuard(self.guard_params, identities)
        self._sock: socket.socket | None = None
        # udpin: one socket connected to each pinned source (see _attach_pinned)
        self._pinned_socks: dict[tuple[str, int], socket.socket] = {}
        self.limits = limits or ValueLimits()
        self._clock_ns = clock_ns
        self._on_rx, self._on_tx = on_rx, on_tx
        self.last_tx_ns: int | None = None  # monotonic ns right after the last frame's send
        self._queue_size = queue_size
        self._queue_frames = queue_frames
        self.counters: Counter[str] = Counter()
        self._verifier = (
            SignatureVerifier(signing_key, allow_unsigned_msgids) if signing_key else None
        )
        # Encoder: never used to parse (so pymavlink's own signature check never runs).
        self._enc = mavlink2.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        if signing_key:
            self._enc.signing.secret_key = signing_key
            self._enc.signing.sign_outgoing = True
            self._enc.signing.link_id = signing_link_id
            self._enc.signing.timestamp = signing_timestamp_now()
        self._rx = ReceivePath(rules, self.guard, self.guard_params, self.limits,
                               self._verifier, self._enc, self.counters, on_reject)
        self._stream_parser: Any = None
        self._dgram_parser: Any = new_parser()  # reset per datagram (reset_parser)
        self._queue: asyncio.Queue[Any] | None = None
        self._transport: Any = None
        self._serial_fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._peer: tuple[str, int] | None = None
        self._closed = False
        self._error: LinkError | None = None
        self._t_open_ns = 0

    @classmethod
    def from_config(cls, mavlink_cfg: Any, target_cfg: Any, **kwargs: Any) -> MavlinkLink:
        """Build from :class:`companion.config.MavlinkConfig` and ``TargetConfig`` (the AGV's
        sysid/compid for FOLLOW_TARGET). Loads the signing key file if one is configured."""
        key = (
            load_signing_key(mavlink_cfg.signing_key_file) if mavlink_cfg.signing_key_file else None
        )
        kwargs.setdefault(
            "allow",
            default_allow_rules(
                mavlink_cfg.target_system,
                mavlink_cfg.target_component,
                target_cfg.mavlink_sysid,
                target_cfg.mavlink_compid,
            ),
        )
        kwargs.setdefault("queue_frames", kwargs.get("on_rx") is None)
        kwargs.setdefault("guard", GuardParams(
            pin_source=bool(getattr(mavlink_cfg, "pin_source", True)),
            allowed_sources=tuple(getattr(mavlink_cfg, "allowed_sources", ())),
            repin_after_s=float(getattr(mavlink_cfg, "repin_after_s", 5.0)),
            max_datagram_bytes=int(getattr(mavlink_cfg, "max_datagram_bytes", 2048)),
            max_datagrams_per_wakeup=int(getattr(mavlink_cfg, "max_datagrams_per_wakeup", 256)),
            untrusted_parse_per_s=float(getattr(mavlink_cfg, "untrusted_parse_per_s", 500.0)),
            reject_log_per_s=float(getattr(mavlink_cfg, "reject_log_per_s", 200.0)),
            recv_buffer_bytes=int(getattr(mavlink_cfg, "recv_buffer_bytes", 4 << 20)),
        ))
        return cls(
            mavlink_cfg.url,
            source_system=mavlink_cfg.source_system,
            source_component=mavlink_cfg.source_component,
            target_system=mavlink_cfg.target_system,
            target_component=mavlink_cfg.target_component,
            signing_key=key,
            **kwargs,
        )

    # -- lifecycle ------------------------------------------------------------------------------

    async def __aenter__(self) -> MavlinkLink:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    async def open(self) -> None:
        """Open the transport (bind / connect / open the serial device)."""
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue(maxsize=self._queue_size + 1)  # +1: room for the sentinel
        self._t_open_ns = self._clock_ns()
        ep = self.endpoint
        try:
            if ep.kind == "udpin":
                self._open_udp((ep.host, ep.port))
            elif ep.kind == "udpout":
                self._peer = (socket.gethostbyname(ep.host), ep.port)
                self._open_udp(("0.0.0.0", 0))
            elif ep.kind == "tcp":
                self._stream_parser = new_parser()
                self._transport, _ = await self._loop.create_connection(
                    lambda: StreamProtocol(self._on_stream_data, self._on_connection_lost),
                    ep.host, ep.port)
            else:
                self._stream_parser = new_parser()
                self._serial_fd = open_serial(ep)
                self._loop.add_reader(self._serial_fd, self._on_serial_readable)
        except OSError as e:
            raise LinkError(f"cannot open MAVLink link {ep}: {e}") from e
        log.info("MAVLink link open: %s (local %s)", ep, self.local_address)

    def _open_udp(self, local: tuple[str, int]) -> None:
        """A non-blocking UDP socket read in batches by :meth:`_on_udp_readable` (asyncio's
        datagram transport reads one datagram per loop iteration: under a flood the kernel
        buffer overflows and drops the real vehicle's datagrams with the garbage)."""
        assert self._loop is not None
        sock = bound_udp_socket(local, self.guard_params.recv_buffer_bytes)
        self._sock = sock
        self._loop.add_reader(sock.fileno(), self._on_udp_readable, sock)

    def _attach_pinned(self, addr: tuple[str, int]) -> None:
        """Give a pinned source its own socket, bound to our port and connected to it: the
        kernel then delivers that source's datagrams there (a connected socket matches better
        than the bound one), in a buffer a flood from other addresses cannot fill, read on
        every loop iteration. Everything else stays on the bound socket."""
        if (self.endpoint.kind != "udpin" or self._sock is None or self._loop is None
                or addr in self._pinned_socks):
            return
        for old in [a for a in self._pinned_socks if not self.guard.is_pinned_address(a)]:
            self._detach_pinned(old)
        try:
            sock = connected_udp_socket(self._sock, addr, self.guard_params.recv_buffer_bytes)
        except OSError as e:
            self._count("pinned_socket_error")
            log.warning("MAVLink: no dedicated socket for %s:%d (%s); sharing the bound one",
                        *addr, e)
            return
        self._pinned_socks[addr] = sock
        self._loop.add_reader(sock.fileno(), self._on_udp_readable, sock)

    def _detach_pinned(self, addr: tuple[str, int]) -> None:
        sock = self._pinned_socks.pop(addr, None)
        if sock is not None:
            if self._loop is not None:
                self._loop.remove_reader(sock.fileno())
            sock.close()

    def _on_udp_readable(self, sock: socket.socket) -> None:
        for _ in range(self.guard_params.max_datagrams_per_wakeup):
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # ICMP port unreachable and the like
                self._count("socket_error")
                log.debug("MAVLink UDP socket error: %s", e)
                continue
            self._on_datagram(data, addr)
        self._count("batch_limit")  # more waiting: read on the next loop iteration

    def close(self) -> None:
        """Close the transport; a pending ``async for`` ends."""
        if self._closed:
            return
        self._closed = True
        if self._transport is not None:
            self._transport.close()
        for a in list(self._pinned_socks):
            self._detach_pinned(a)
        if self._sock is not None:
            if self._loop is not None:
                self._loop.remove_reader(self._sock.fileno())
            self._sock.close()
        if self._serial_fd is not None:
            if self._loop is not None:
                self._loop.remove_reader(self._serial_fd)
            os.close(self._serial_fd)
            self._serial_fd = None
        self._push(_CLOSED)

    # -- properties -----------------------------------------------------------------------------

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Bound (host, port) of a UDP/TCP socket (useful with ``udpin:127.0.0.1:0``)."""
        if self._sock is not None:
            addr = self._sock.getsockname()
        elif self._transport is None:
            return None
        else:
            addr = self._transport.get_extra_info("sockname")
        return (addr[0], addr[1]) if addr else None

    @property
    def peer_address(self) -> tuple[str, int] | None:
        """Where frames are sent (udpin: learned from the autopilot's accepted frames)."""
        return self._peer

    @property
    def has_peer(self) -> bool:
        return self._peer is not None or self.endpoint.kind in ("tcp", "serial")

    def boot_time_ms(self) -> int:
        """Milliseconds since the link opened (``time_boot_ms`` of what we send)."""
        return ((self._clock_ns() - self._t_open_ns) // 1_000_000) & 0xFFFFFFFF

    # -- receive --------------------------------------------------------------------------------

    def __aiter__(self) -> MavlinkLink:
        return self

    async def __anext__(self) -> Received:
        if self._queue is None:
            raise LinkError("link is not open")
        item = await self._queue.get()
        if item is _CLOSED:
            self._push(_CLOSED)  # wake any other waiter too
            if self._error is not None:
                raise self._error
            raise StopAsyncIteration
        assert isinstance(item, Received)
        return item

    async def recv(self, timeout_s: float | None = None) -> Received:
        """Next accepted frame; ``TimeoutError`` after ``timeout_s``; LinkError when closed."""
        try:
            return await asyncio.wait_for(self.__anext__(), timeout_s)
        except StopAsyncIteration:
            raise LinkError("link closed") from None

    def pending(self) -> int:
        """Frames waiting in the receive queue."""
        return 0 if self._queue is None else self._queue.qsize()

    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] += n

    def _push(self, item: Any) -> None:
        q = self._queue
        if q is None:
            return
        if item is not _CLOSED and q.qsize() >= self._queue_size:
            q.get_nowait()
            self._count("queue_overflow")
        if q.full():  # only the sentinel can hit this
            q.get_nowait()
        q.put_nowait(item)

    def _on_datagram(self, data: bytes, addr: Any) -> None:
        if self._closed:
            return
        self.counters["rx_datagrams"] += 1
        self.counters["rx_bytes"] += len(data)
        t = self._clock_ns()
        addr = (addr[0], addr[1])
        why = self.guard.admit(data, addr, t)
        if why is not None:
            self._rx.reject(why, data, t)
            return
        rx = self._rx.accept_datagram(data, t, addr)  # one frame: no parser (wire.py)
        if rx is not False:  # accepted, or rejected / unused (counted)
            if rx is not None:
                self._accepted(rx, t, addr)
            return
        # reset per datagram: one bad datagram cannot poison others
        parser = reset_parser(self._dgram_parser)
        for m in self._parse(parser, data):
            self._handle(m, t, addr)
        if parser.buf_len() > 0:
            self._rx.reject("incomplete", bytes(parser.buf[parser.buf_index :]), t)

    def _on_stream_data(self, data: bytes) -> None:
        if self._closed:
            return
        self._count("rx_bytes", len(data))
        t = self._clock_ns()
        for m in self._parse(self._stream_parser, data):
            self._handle(m, t, None)

    def _on_serial_readable(self) -> None:
        assert self._serial_fd is not None
        try:
            data = os.read(self._serial_fd, 4096)
        except BlockingIOError:
            return
        except OSError as e:  # EIO: the other end went away (pty closed, USB unplugged)
            self._on_connection_lost(e)
            return
        if data:
            self._on_stream_data(data)

    def _on_connection_lost(self, exc: Exception | None) -> None:
        if not self._closed:
            self._error = LinkError(f"MAVLink link {self.endpoint} lost: {exc or 'closed by peer'}")
            log.warning("%s", self._error)
            self.close()

    def _parse(self, parser: Any, data: bytes) -> list[Any]:
        try:
            return parser.parse_buffer(data) or []
        except Exception as e:  # hostile input must never unwind the event loop
            self._rx.reject("parser_error", data, self._clock_ns())
            log.debug("pymavlink parser raised %r", e)
            # a stream parser in an unknown state is replaced
            if parser is self._stream_parser:
                self._stream_parser = new_parser()
            return []

    def _handle(self, m: Any, t_ns: int, addr: Any) -> None:
        rx = self._rx.accept(m, t_ns, addr)
        if rx is not None:
            self._accepted(rx, t_ns, addr)

    def _accepted(self, rx: Received, t_ns: int, addr: Any) -> None:
        sysid, compid = rx.src_sysid, rx.src_compid
        is_autopilot = sysid == self.target_system and (
            self.target_component == 0 or compid == self.target_component)
        if addr is not None and self.guard.on_valid(sysid, compid, rx.name, addr, t_ns):
            self._attach_pinned(addr)
        if self.endpoint.kind == "udpin" and addr is not None and is_autopilot:
            if not self.guard_params.pin_source:
                self._peer = (addr[0], addr[1])
            elif (pinned := self.guard.pinned(sysid)) is not None:
                self._peer = pinned
            elif self._peer is None:
                self._peer = (addr[0], addr[1])  # telemetry before the first HEARTBEAT
        self.counters["rx_accepted"] += 1
        if self._on_rx is not None:
            self._on_rx(rx)
        if self._queue_frames:  # False: on_rx does the work (a task wake-up a frame saved)
            self._push(rx)

    # -- send (companion/link/sending.py) --------------------------------------------------------

    @property
    def mav(self) -> Any:
        """The pymavlink encoder: ``link.mav.xxx_encode(...)`` builds a message for :meth:`send`."""
        return self._enc
