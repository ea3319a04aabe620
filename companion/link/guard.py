"""Who may speak for the vehicle, and how much work a datagram may cost: the UDP receive guard.

Over plain UDP anyone on the network can send frames claiming the autopilot's sysid/compid, and
a flood of garbage competes with the real telemetry for the one socket. The guard, consulted by
:class:`companion.link.link.MavlinkLink` for every datagram BEFORE it is parsed:

- **Source pinning** (``mavlink.pin_source``): a protected identity (the autopilot, the AGV) is
  pinned to the (host, port) its first valid frame came from (for the autopilot: its first
  valid HEARTBEAT, after every check of the receive path, signature included). From then on a
  datagram from another address that claims a pinned identity (a MAVLink 1 or 2 header anywhere
  in it with that sysid) is dropped unparsed (``spoofed_source``). Addresses in
  ``mavlink.allowed_sources`` (``"host"`` or ``"host:port"``, e.g. a mavlink-router's ports)
  may always speak. A pin is released when its address has sent nothing valid for
  ``mavlink.repin_after_s`` (an autopilot that restarted on another port is found again).
- **Bounded work**: datagrams longer than ``max_datagram_bytes`` are dropped unparsed
  (``oversize``); datagrams from addresses that are neither pinned nor allowed are parsed at
  most ``untrusted_parse_per_s`` per second (token bucket, ``untrusted_burst`` deep; beyond it
  ``rate_limited``, unparsed). Rejected frames reach the log at most ``reject_log_per_s``
  per second (5 s burst; all are counted). The link itself reads at most
  ``max_datagrams_per_wakeup`` datagrams per event-loop wake-up, so the control loop runs
  between batches, and gives every pinned source a socket of its own (connected to it, on the
  same port): a flood from other addresses fills the bound socket's buffer, never the one the
  real vehicle's datagrams arrive in.

Before an identity is pinned, the first valid frame wins: an attacker already on the network
before the vehicle's first HEARTBEAT could take the pin. MAVLink 2 signing closes that gap.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from companion.link.errors import LinkError

log = logging.getLogger(__name__)

_V2, _V1 = 0xFD, 0xFE


@dataclass(frozen=True)
class GuardParams:
    """Receive-guard settings (see the module docstring); ``mavlink.*`` keys of the config."""

    pin_source: bool = True
    allowed_sources: tuple[str, ...] = ()
    repin_after_s: float = 5.0
    max_datagram_bytes: int = 2048
    max_datagrams_per_wakeup: int = 256
    untrusted_parse_per_s: float = 500.0
    untrusted_burst: int = 256
    reject_log_per_s: float = 200.0
    recv_buffer_bytes: int = 4 << 20

    def __post_init__(self) -> None:
        for name in ("max_datagram_bytes", "max_datagrams_per_wakeup", "untrusted_burst",
                     "recv_buffer_bytes"):
            if getattr(self, name) < 1:
                raise LinkError(f"{name} must be >= 1")
        for name in ("repin_after_s", "untrusted_parse_per_s", "reject_log_per_s"):
            if not getattr(self, name) > 0:
                raise LinkError(f"{name} must be > 0")
        for s in self.allowed_sources:
            parse_source(s)


def parse_source(text: str) -> tuple[str, int | None]:
    """``"127.0.0.1"`` -> (host, None: any port); ``"127.0.0.1:14580"`` -> (host, port)."""
    host, sep, port = text.strip().rpartition(":")
    if not sep:
        host, port = text.strip(), ""
    parts = host.split(".")
    if len(parts) != 4 or not all(p.isdigit() and int(p) <= 255 for p in parts):
        raise LinkError(f"allowed source {text!r}: expected an IPv4 address, optionally :PORT")
    if port == "":
        return host, None
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise LinkError(f"allowed source {text!r}: port must be 1..65535")
    return host, int(port)


def claimed_sysids(data: bytes) -> set[int]:
    """Every sysid a MAVLink 1 or 2 header anywhere in ``data`` would claim (over-approximate:
    any magic byte with room for a header counts)."""
    out: set[int] = set()
    n = len(data)
    for magic, off, hdr in ((_V2, 5, 10), (_V1, 3, 6)):
        i = data.find(magic)
        while 0 <= i <= n - hdr:
            out.add(data[i + off])
            i = data.find(magic, i + 1)
    return out


@dataclass
class _Pin:
    sysid: int
    compid: int | None
    pin_on: str | None  # message that pins (None: any valid frame)
    addr: tuple[str, int] | None = None
    last_valid_ns: int = 0


class SourceGuard:
    """Per-datagram admission (:meth:`admit`) and pinning (:meth:`on_valid`). ``identities``:
    (sysid, compid or None, message name that pins or None for any valid frame)."""

    def __init__(self, params: GuardParams,
                 identities: Sequence[tuple[int, int | None, str | None]]) -> None:
        self.params = params
        self._pins = [_Pin(s, c, m) for s, c, m in identities]
        self._allowed = [parse_source(s) for s in params.allowed_sources]
        self._tokens = float(params.untrusted_burst)
        self._t_tokens_ns: int | None = None
        self.counters: Counter[str] = Counter()

    # -- queries ----------------------------------------------------------------------------

    def pinned(self, sysid: int) -> tuple[str, int] | None:
        for p in self._pins:
            if p.sysid == sysid and p.addr is not None:
                return p.addr
        return None

    def is_pinned_address(self, addr: tuple[str, int]) -> bool:
        return any(p.addr == addr for p in self._pins)

    def allowed(self, addr: tuple[str, int]) -> bool:
        return any(h == addr[0] and (pt is None or pt == addr[1]) for h, pt in self._allowed)

    def _live(self, p: _Pin, t_ns: int) -> bool:
        return p.addr is not None and (
            t_ns - p.last_valid_ns <= self.params.repin_after_s * 1e9)

    def trusted(self, addr: tuple[str, int], t_ns: int) -> bool:
        if self._allowed and self.allowed(addr):
            return True
        for p in self._pins:  # noqa: SIM110 - every datagram: a plain loop, no generator
            if p.addr == addr and self._live(p, t_ns):
                return True
        return False

    # -- admission --------------------------------------------------------------------------

    def admit(self, data: bytes, addr: tuple[str, int], t_ns: int) -> str | None:
        """Reason to drop ``data`` from ``addr`` unparsed, or None to parse it."""
        prm = self.params
        if len(data) > prm.max_datagram_bytes:
            return "oversize"
        if self.trusted(addr, t_ns):
            return None
        if prm.pin_source:
            claims = claimed_sysids(data)
            for p in self._pins:
                if p.sysid in claims and self._live(p, t_ns):
                    return "spoofed_source"
        if self._t_tokens_ns is not None:
            dt = (t_ns - self._t_tokens_ns) * 1e-9
            self._tokens = min(float(prm.untrusted_burst),
                               self._tokens + max(dt, 0.0) * prm.untrusted_parse_per_s)
        self._t_tokens_ns = t_ns
        if self._tokens < 1.0:
            return "rate_limited"
        self._tokens -= 1.0
        return None

    def frame_source_ok(self, sysid: int, compid: int, addr: tuple[str, int] | None,
                        t_ns: int) -> bool:
        """After parsing: a frame of a pinned identity from elsewhere is refused (defence in
        depth behind :meth:`admit`)."""
        if addr is None or not self.params.pin_source or (self._allowed and self.allowed(addr)):
            return True
        for p in self._pins:
            if p.sysid == sysid and (p.compid is None or p.compid == compid) \
                    and self._live(p, t_ns) and p.addr != addr:
                return False
        return True

    def on_valid(self, sysid: int, compid: int, name: str, addr: tuple[str, int] | None,
                 t_ns: int) -> bool:
        """A frame passed every check: refresh or set its identity's pin. Returns True when
        this frame (re)pinned an identity."""
        if addr is None or not self.params.pin_source:
            return False
        pinned_now = False
        for p in self._pins:
            if p.sysid != sysid or (p.compid is not None and p.compid != compid):
                continue
            if p.addr == addr:
                p.last_valid_ns = t_ns
            elif not self._live(p, t_ns) and (p.pin_on is None or p.pin_on == name):
                if p.addr is not None:
                    self.counters["repinned"] += 1
                    log.warning("MAVLink: sysid %d moved from %s:%d to %s:%d (silent for "
                                "%.1f s)", sysid, *p.addr, *addr, self.params.repin_after_s)
                else:
                    log.info("MAVLink: sysid %d pinned to %s:%d", sysid, *addr)
                p.addr, p.last_valid_ns = addr, t_ns
                pinned_now = True
        return pinned_now
