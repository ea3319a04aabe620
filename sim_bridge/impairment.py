"""Network impairment of one MAVLink link: the pure core (no sockets, no clocks).

Like the message interception of MAVSDK's system tests, or ``tc netem`` on a real link, but
seeded and configured per scenario (``[sim.impairment]``, docs/reference/wire.md). Each direction
of a link has its own :class:`DirectionImpairment`; :meth:`DirectionImpairment.process` takes the
time a datagram was sent (``t_s``, seconds of emulator boot time: wall time in realtime,
simulated time in lockstep) and the datagram, and returns what the other end receives: a list
of :class:`Delivery` (``deliver_at_s``, bytes), possibly empty (dropped), possibly two
(duplicated), possibly with flipped bits (corrupted).

Per datagram, in this order:

1. inside a link cut window ``[t_start_s, t_end_s)``: dropped (both directions);
2. vehicle -> peer only: a HEARTBEAT frame (MAVLink 2, msgid 0) at or after
   ``heartbeat_stop_s`` is dropped (the vehicle "stops sending HEARTBEAT");
3. dropped with probability ``drop_p``;
4. ``corrupt_bits`` distinct random bits flipped with probability ``corrupt_p``;
5. delivered at ``t_s + delay_s + U(0, jitter_s)``, but never before the previous in-order
   datagram of this direction (jitter alone keeps the order, as on one network path); with
   probability ``reorder_p`` it is instead held back ``reorder_delay_s`` more and skips that
   ordering rule, so datagrams sent after it overtake it;
6. duplicated with probability ``duplicate_p``: the copy arrives right after the original.

Every random draw comes from one ``random.Random`` per direction, seeded from the scenario
seed, the link's name and the direction, so a run is reproducible and the two directions (and
links) are independent.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

MAVLINK2_MAGIC = 0xFD
HEARTBEAT_MSGID = 0

# Direction names (the emulator is the vehicle; the peer is the companion or a GCS)
VEHICLE_TO_PEER = "vehicle_to_companion"
PEER_TO_VEHICLE = "companion_to_vehicle"


def _prob(name: str, p: float) -> None:
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"{name}: must be in [0, 1], got {p}")


@dataclass(frozen=True)
class ImpairmentParams:
    """What one direction of a link does to its datagrams. Probabilities are per datagram."""

    drop_p: float = 0.0
    duplicate_p: float = 0.0
    reorder_p: float = 0.0
    reorder_delay_s: float = 0.05
    delay_s: float = 0.0
    jitter_s: float = 0.0
    corrupt_p: float = 0.0
    corrupt_bits: int = 1

    def __post_init__(self) -> None:
        for name in ("drop_p", "duplicate_p", "reorder_p", "corrupt_p"):
            _prob(name, getattr(self, name))
        for name in ("reorder_delay_s", "delay_s", "jitter_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}: must be >= 0")
        if self.corrupt_bits < 1:
            raise ValueError("corrupt_bits: must be >= 1")

    @property
    def active(self) -> bool:
        return any((self.drop_p, self.duplicate_p, self.reorder_p, self.delay_s,
                    self.jitter_s, self.corrupt_p))


@dataclass(frozen=True)
class Delivery:
    """A datagram the other end receives at ``deliver_at_s`` (emulator boot time, s)."""

    deliver_at_s: float
    data: bytes


@dataclass
class ImpairmentCounters:
    """What one direction did (counts of datagrams since the link opened)."""

    datagrams: int = 0
    delivered: int = 0       # deliveries handed on, duplicates included
    dropped: int = 0         # random drops
    cut: int = 0             # dropped inside a link cut window
    heartbeats_stopped: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    delayed: int = 0         # delivered later than sent


def msgid_of(data: bytes) -> int | None:
    """The message id of a MAVLink 2 frame at the start of ``data`` (None if it is not one)."""
    if len(data) < 10 or data[0] != MAVLINK2_MAGIC:
        return None
    return data[7] | (data[8] << 8) | (data[9] << 16)


def flip_bits(data: bytes, n_bits: int, rng: random.Random) -> bytes:
    """``data`` with ``min(n_bits, 8 len(data))`` distinct bits flipped."""
    if not data:
        return data
    out = bytearray(data)
    for bit in rng.sample(range(8 * len(out)), min(n_bits, 8 * len(out))):
        out[bit >> 3] ^= 1 << (bit & 7)
    return bytes(out)


@dataclass
class DirectionImpairment:
    """One direction of one link. Not thread-safe (the emulator runs on one event loop)."""

    params: ImpairmentParams
    seed: int | str = 0
    cuts_s: tuple[tuple[float, float], ...] = ()
    heartbeat_stop_s: float | None = None  # vehicle -> peer only; None = never
    counters: ImpairmentCounters = field(default_factory=ImpairmentCounters)

    def __post_init__(self) -> None:
        self._rng = random.Random(str(self.seed))
        self._last_in_order_s = float("-inf")

    def in_cut(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.cuts_s)

    def process(self, t_s: float, data: bytes) -> list[Delivery]:
        """What the other end receives of ``data`` sent at ``t_s``; deliveries in time order."""
        c, p, rng = self.counters, self.params, self._rng
        c.datagrams += 1
        if self.in_cut(t_s):
            c.cut += 1
            return []
        if (self.heartbeat_stop_s is not None and t_s >= self.heartbeat_stop_s
                and msgid_of(data) == HEARTBEAT_MSGID):
            c.heartbeats_stopped += 1
            return []
        # draw the same numbers for every datagram, used or not, so that changing one
        # probability reshuffles the others' outcomes as little as possible
        u_drop, u_corrupt, u_reorder, u_dup = (rng.random() for _ in range(4))
        jitter = rng.uniform(0.0, p.jitter_s) if p.jitter_s > 0 else 0.0
        if u_drop < p.drop_p:
            c.dropped += 1
            return []
        if u_corrupt < p.corrupt_p:
            data = flip_bits(data, p.corrupt_bits, rng)
            c.corrupted += 1
        at = t_s + p.delay_s + jitter
        if u_reorder < p.reorder_p:
            at += p.reorder_delay_s
            c.reordered += 1
        else:
            at = max(at, self._last_in_order_s)
            self._last_in_order_s = at
        out = [Delivery(at, data)]
        if u_dup < p.duplicate_p:
            out.append(Delivery(at, data))
            c.duplicated += 1
        if at > t_s:
            c.delayed += 1
        c.delivered += len(out)
        return out


@dataclass
class LinkImpairment:
    """Both directions of one link: ``outgoing`` (vehicle -> peer), ``incoming`` (peer ->
    vehicle). Cuts apply to both; the heartbeat stop to ``outgoing`` only."""

    outgoing: DirectionImpairment
    incoming: DirectionImpairment

    @classmethod
    def build(cls, link_name: str, seed: int, to_peer: ImpairmentParams,
              from_peer: ImpairmentParams, cuts_s: tuple[tuple[float, float], ...] = (),
              heartbeat_stop_s: float | None = None) -> LinkImpairment:
        return cls(
            DirectionImpairment(to_peer, f"{seed}:{link_name}:{VEHICLE_TO_PEER}", cuts_s,
                                heartbeat_stop_s),
            DirectionImpairment(from_peer, f"{seed}:{link_name}:{PEER_TO_VEHICLE}", cuts_s))
