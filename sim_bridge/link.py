"""MAVLink 2 over UDP (pymavlink), the way the emulated PX4 talks to its peers.

One :class:`MavUdpLink` per PX4 "instance" (offboard API link, GCS link) and one for the AGV's
own node. Receive path (docs/reference/pitfalls.md, pymavlink): every datagram is parsed by a FRESH
robust parser, so a truncated or corrupted datagram cannot poison the next ones; ``BAD_DATA`` and
``UNKNOWN_<id>`` pseudo-messages are counted and dropped, MAVLink 1 frames are counted and
dropped, frames from our own (sysid, compid) are dropped, and messages addressed to another
system/component are counted as foreign and not delivered.

Send path: telemetry goes to the configured remote plus every address that sent us a valid
MAVLink 2 message (so a client that binds elsewhere, like MAVSDK with ``udpin``, is served as
PX4 serves it); replies (ACKs, requested messages) go to the sender's address only.

Optional, both off by default:

* Signing (``signing``, a shared :class:`~sim_bridge.signing.SigningState`): every outgoing
  frame is signed (link id ``signing_link_id``) and every incoming one verified before it is
  dispatched; rejects are counted (``rx_unsigned``, ``rx_bad_signature``, ``rx_replayed``).
* Impairment (``impairment``, a :class:`~sim_bridge.impairment.LinkImpairment`): every datagram
  in either direction goes through it, stamped with ``time_s()`` (boot time). What it delays
  is sent/dispatched later: with ``deferred=False`` (realtime) by the event loop's timer, with
  ``deferred=True`` (lockstep: delays count in simulated time) when the runtime calls
  :meth:`MavUdpLink.pump` with the simulated time. ``on_raw_datagram`` sees every received
  datagram before the impairment (the lockstep runtime uses it to know that a setpoint was
  sent even if the network then loses it).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge import LinkError, mavpack
from sim_bridge.impairment import LinkImpairment
from sim_bridge.signing import SigningState, Verdict

log = logging.getLogger(__name__)

Address = tuple[str, int]
MessageHandler = Callable[["MavUdpLink", Any, Address], None]

PEER_TIMEOUT_S = 10.0
MAX_PEERS = 16
MAVLINK2_MAGIC = 0xFD


@dataclass(frozen=True)
class LinkCounters:
    """Receive/send statistics of one link (monotonic counts since it opened)."""

    rx_datagrams: int = 0
    rx_bytes: int = 0
    rx_messages: int = 0   # valid MAVLink 2 messages delivered to the handler
    rx_bad: int = 0        # BAD_DATA pseudo-messages (bad CRC, garbage, truncation)
    rx_unknown: int = 0    # unknown message ids
    rx_mavlink1: int = 0   # MAVLink 1 frames (dropped: 16-bit CRC lets garbage through)
    rx_foreign: int = 0    # addressed to another system/component
    rx_own: int = 0        # our own frames echoed back
    rx_empty: int = 0      # datagrams that yielded no message at all
    tx_messages: int = 0
    tx_errors: int = 0
    rx_unsigned: int = 0         # signing on: unsigned frame of an id that must be signed
    rx_bad_signature: int = 0    # signing on: signature does not verify (no state changed)
    rx_replayed: int = 0         # signing on: stale timestamp (replay, old or too many streams)
    rx_unsigned_allowed: int = 0  # signing on: unsigned RADIO_STATUS/ADSB_VEHICLE/COLLISION


class _Sink:
    """File-like object pymavlink writes packed frames into."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, b: bytes) -> None:
        self.frames.append(bytes(b))


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, link: MavUdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.link._on_datagram(data, (addr[0], addr[1]))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when nobody listens yet: normal for UDP telemetry
        log.debug("%s: socket error %s", self.link.name, exc)


class MavUdpLink:
    """A UDP MAVLink 2 endpoint. ``async with MavUdpLink(...) as link:``; ``link.port`` is the
    bound local port (useful when ``local_port`` is 0)."""

    def __init__(self, name: str, local_host: str, local_port: int, remote: Address | None,
                 sysid: int, compid: int, handler: MessageHandler | None = None,
                 clock: Callable[[], float] = time.monotonic, *,
                 signing: SigningState | None = None, signing_link_id: int = 0,
                 impairment: LinkImpairment | None = None,
                 time_s: Callable[[], float] | None = None, deferred: bool = False,
                 on_raw_datagram: Callable[[bytes], None] | None = None) -> None:
        self.name = name
        self.local_host = local_host
        self.local_port = local_port
        self.remote = remote
        self.sysid = sysid
        self.compid = compid
        self.handler = handler
        self._clock = clock
        self._sink = _Sink()
        self.mav = mavlink2.MAVLink(self._sink, srcSystem=sysid, srcComponent=compid)
        self._transport: asyncio.DatagramTransport | None = None
        self._peers: dict[Address, float] = {}
        self._c: dict[str, int] = dict.fromkeys(LinkCounters.__dataclass_fields__, 0)
        self.signing = signing
        if signing is not None:
            self.mav.signing.secret_key = signing.key
            self.mav.signing.link_id = signing_link_id
            self.mav.signing.sign_outgoing = True
        self.impairment = impairment
        self._time_s = time_s if time_s is not None else clock
        self._deferred = deferred
        self._on_raw = on_raw_datagram
        self._pending: list[tuple[float, int, Callable[[], None]]] = []
        self._pending_seq = itertools.count()
        self._timers: set[asyncio.TimerHandle] = set()

    # ------------------------------------------------------------------ lifecycle
    async def open(self) -> MavUdpLink:
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _Protocol(self), local_addr=(self.local_host, self.local_port))
        except OSError as e:
            raise LinkError(f"{self.name}: cannot bind UDP {self.local_host}:{self.local_port}"
                            f" ({e.strerror})") from e
        self._transport = transport
        self.port = transport.get_extra_info("sockname")[1]
        return self

    def close(self) -> None:
        for h in self._timers:
            h.cancel()
        self._timers.clear()
        self._pending.clear()
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    async def __aenter__(self) -> MavUdpLink:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    @property
    def counters(self) -> LinkCounters:
        return LinkCounters(**self._c)

    @property
    def peers(self) -> list[Address]:
        now = self._clock()
        out = [self.remote] if self.remote is not None else []
        out += [a for a, t in self._peers.items()
                if now - t <= PEER_TIMEOUT_S and a != self.remote]
        return out

    # ------------------------------------------------------------------ impairment timing
    def _schedule(self, at_s: float, now_s: float, fn: Callable[[], None]) -> None:
        if at_s <= now_s:
            fn()
        elif self._deferred:
            heapq.heappush(self._pending, (at_s, next(self._pending_seq), fn))
        else:
            loop = asyncio.get_running_loop()
            handle: asyncio.TimerHandle

            def fire() -> None:
                self._timers.discard(handle)
                fn()

            handle = loop.call_later(at_s - now_s, fire)
            self._timers.add(handle)

    def next_due_s(self) -> float | None:
        """Boot time of the earliest deferred delivery (lockstep), or None."""
        return self._pending[0][0] if self._pending else None

    def pump(self, t_s: float) -> int:
        """Send/dispatch every deferred delivery due by ``t_s``, in time order; returns how many."""
        n = 0
        while self._pending and self._pending[0][0] <= t_s:
            _, _, fn = heapq.heappop(self._pending)
            fn()
            n += 1
        return n

    # ------------------------------------------------------------------ receive
    def _on_datagram(self, data: bytes, addr: Address) -> None:
        imp = self.impairment
        if imp is None:
            self._receive(data, addr)
            return
        if self._on_raw is not None:
            self._on_raw(data)
        now = self._time_s()
        for d in imp.incoming.process(now, data):
            self._schedule(d.deliver_at_s, now,
                           lambda b=d.data: self._receive(b, addr))  # type: ignore[misc]

    def _receive(self, data: bytes, addr: Address) -> None:
        c = self._c
        c["rx_datagrams"] += 1
        c["rx_bytes"] += len(data)
        # one plain frame (a setpoint, every step in lockstep) without pymavlink's parser
        msg = mavpack.unpack(data, mavlink2)
        if msg is not None:
            self._dispatch(msg, addr)
            return
        parser = mavlink2.MAVLink(None)  # fresh per datagram (pitfalls.md)
        parser.robust_parsing = True
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:  # robust parsing should not raise; count anything that does
            log.debug("%s: parser raised on a datagram from %s", self.name, addr, exc_info=True)
            c["rx_bad"] += 1
            return
        if not msgs:
            c["rx_empty"] += 1
            return
        for msg in msgs:
            self._dispatch(msg, addr)

    def _dispatch(self, msg: Any, addr: Address) -> None:
        c = self._c
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            c["rx_bad"] += 1
            return
        if mtype.startswith("UNKNOWN_"):
            c["rx_unknown"] += 1
            return
        buf = msg.get_msgbuf()
        if not buf or buf[0] != MAVLINK2_MAGIC:
            c["rx_mavlink1"] += 1
            return
        if msg.get_srcSystem() == self.sysid and msg.get_srcComponent() == self.compid:
            c["rx_own"] += 1
            return
        if self.signing is not None and not self._signature_ok(bytes(buf), mtype):
            return
        ts = getattr(msg, "target_system", None)
        tc = getattr(msg, "target_component", None)
        if (ts is not None and ts not in (0, self.sysid)) or (
                tc is not None and tc not in (0, self.compid)):
            c["rx_foreign"] += 1
            return
        c["rx_messages"] += 1
        now = self._clock()
        if addr not in self._peers and len(self._peers) >= MAX_PEERS:
            self._peers = {a: t for a, t in self._peers.items() if now - t <= PEER_TIMEOUT_S}
            if len(self._peers) >= MAX_PEERS:  # still full of live peers: replace the oldest
                del self._peers[min(self._peers, key=self._peers.__getitem__)]
        self._peers[addr] = now
        if self.handler is not None:
            try:
                self.handler(self, msg, addr)
            except Exception:
                log.exception("%s: handler failed on %s from %s", self.name, mtype, addr)

    def _signature_ok(self, frame: bytes, mtype: str) -> bool:
        assert self.signing is not None
        v = self.signing.verify(frame)
        if v is Verdict.SIGNED:
            return True
        if v is Verdict.UNSIGNED_ALLOWED:
            self._c["rx_unsigned_allowed"] += 1
            return True
        key = {Verdict.UNSIGNED: "rx_unsigned", Verdict.BAD_SIGNATURE: "rx_bad_signature",
               Verdict.MALFORMED: "rx_bad"}.get(v, "rx_replayed")
        self._c[key] += 1
        log.debug("%s: rejected %s (%s)", self.name, mtype, v.value)
        return False

    # ------------------------------------------------------------------ send
    def send(self, msg: Any, addr: Address | None = None) -> None:
        """Pack ``msg`` (a pymavlink message from ``self.mav.xxx_encode``, or a
        :class:`~sim_bridge.mavpack.Encoded`) and send it to
        ``addr`` or, without one, to every current peer."""
        self.send_frames(self.pack(msg), addr)

    def pack(self, msg: Any) -> list[bytes]:
        """The wire frames of ``msg`` (takes the link's next sequence number, and the next
        signing timestamp when signing is on, now)."""
        if self.signing is None and mavpack.packable(msg):
            return [mavpack.pack(self.mav, msg)]  # pymavlink's bytes, a third of its cost
        if isinstance(msg, mavpack.Encoded):
            msg = msg.message()
        if self.signing is not None:
            self.mav.signing.timestamp = self.signing.next_timestamp(time.time())
        self.mav.send(msg)
        if self.signing is not None:  # pymavlink counted up once per frame it signed
            self.signing.timestamp = max(self.signing.timestamp, self.mav.signing.timestamp - 1)
        frames, self._sink.frames = self._sink.frames, []
        return frames

    def send_frames(self, frames: list[bytes], addr: Address | None = None) -> None:
        """Send frames packed earlier by :meth:`pack` (to ``addr`` or every current peer)."""
        targets = [addr] if addr is not None else self.peers
        if self._transport is None:
            return
        imp = self.impairment
        now = self._time_s() if imp is not None else 0.0
        for frame in frames:
            for a in targets:
                if imp is None:
                    self._sendto(frame, a)
                    continue
                for d in imp.outgoing.process(now, frame):
                    self._schedule(d.deliver_at_s, now,
                                   lambda b=d.data, a=a: self._sendto(b, a))  # type: ignore[misc]

    def _sendto(self, frame: bytes, addr: Address) -> None:
        if self._transport is None:
            return
        try:
            self._transport.sendto(frame, addr)
            self._c["tx_messages"] += 1
        except OSError:
            self._c["tx_errors"] += 1
