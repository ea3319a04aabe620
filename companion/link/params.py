"""Reading the autopilot's parameters: PARAM_REQUEST_READ by name, PARAM_VALUE back.

The protocol as PX4 serves it (``src/modules/mavlink/mavlink_parameters.cpp``,
https://mavlink.io/en/services/parameter.html):

* PARAM_REQUEST_READ (#20) with ``param_index = -1`` names the parameter by its ``param_id``
  (at most 16 characters, NUL-padded); PX4 answers with one PARAM_VALUE (#22) carrying the
  name, the value, its ``param_type``, the parameter's index and the count.
* Values travel in the float32 ``param_value``; integer types are copied byte-wise
  (PX4 ``memcpy``s an INT32 into the float: MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE),
  so an INT32 of 4001 arrives as the denormal float with the same four bytes.
* An unknown name gets **no answer** (PX4's ``send_param(PARAM_INVALID)`` returns without
  sending; PARAM_ERROR #345 is a work-in-progress message of MAVLink's development dialect
  that PX4 does not send). So a missing parameter can only be told from a lost request by
  waiting: each name is asked up to ``retries`` times and reported missing after that. A
  missing parameter is not an error here: the caller decides.

Retries, as a ground station makes them (MAVSDK's parameter client: one timeout per request,
asked again on its expiry, ``retries`` times; QGroundControl re-requests each parameter it
misses by name): every name has its own deadline and is asked again alone when it passes, so
one lost datagram costs one request, not a round. On a loaded machine or link the answers come
late, not never: a try waits ``timeout_s`` or :data:`RTT_FACTOR` times the slowest answer seen
so far, whichever is longer, and each retry of a name waits twice as long as its previous try
(capped at :data:`MAX_TIMEOUT_FACTOR` x ``timeout_s``), as TCP backs off; an answer is taken
whenever it arrives, also one to an earlier request of the name.

:class:`ParamReader` is fed PARAM_VALUE messages by whoever reads the link (the runtime's
receive callback, which also logs them to the MCAP file like every other message) and sends
its requests through the link.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import struct
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from companion.link.errors import LinkError, NoPeerError

log = logging.getLogger(__name__)

__all__ = ["ParamReadResult", "ParamReader", "ParamValue", "decode_param_value"]

# MAV_PARAM_TYPE -> struct format of the value's bytes at the start of the float32 field
_BYTEWISE = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}
MAV_PARAM_TYPE_REAL32 = 9


def decode_param_value(param_type: int, wire: float) -> float:
    """The value a PARAM_VALUE carries: REAL32 as is, the integer types byte-wise (module
    docstring). Raises ``ValueError`` for a type this reader does not decode (64-bit, double)."""
    if param_type == MAV_PARAM_TYPE_REAL32:
        return float(wire)
    fmt = _BYTEWISE.get(int(param_type))
    if fmt is None:
        raise ValueError(f"param_type {param_type} not decoded (REAL32 or <= 32-bit integers)")
    raw = struct.pack("<f", wire)[: struct.calcsize(fmt)]
    return float(struct.unpack(fmt, raw)[0])


def _name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


@dataclass(frozen=True)
class ParamValue:
    """One parameter as the autopilot sent it (decoded ``value``)."""

    name: str
    value: float
    param_type: int
    index: int
    count: int


@dataclass(frozen=True)
class ParamReadResult:
    """What a read found: ``values`` by name, the ``missing`` names (no answer after every
    retry), the requests sent and the wall time it took."""

    values: Mapping[str, ParamValue] = field(default_factory=dict)
    missing: tuple[str, ...] = ()
    requests_sent: int = 0
    elapsed_s: float = 0.0

    def value(self, name: str) -> float | None:
        p = self.values.get(name)
        return None if p is None else p.value


RTT_FACTOR = 3.0
"""A try waits at least this many times the slowest answer seen so far (a loaded autopilot or
link answers late: asking again sooner only adds requests to its queue)."""
MAX_TIMEOUT_FACTOR = 8.0
"""A try's wait is at most this many times the configured ``timeout_s``."""


class _ReadState:
    """The bookkeeping of one :meth:`ParamReader.read`: per name, the tries made, when it was
    last asked and its deadline; the slowest answer to a name asked once (an answer to a name
    asked twice cannot say which request it answers: Karn's rule, as TCP measures its RTT)."""

    def __init__(self, names: Sequence[str], timeout_s: float, retries: int,
                 clock: Callable[[], float]) -> None:
        self.names, self.timeout_s, self.retries, self.clock = names, timeout_s, retries, clock
        self.tries: dict[str, int] = {}
        self.asked_at: dict[str, float] = {}
        self.deadline: dict[str, float] = {}
        self.answered: set[str] = set()
        self.retried: set[str] = set()
        self.slowest_s = 0.0
        self.sent = 0

    def wait_s(self, tries: int) -> float:
        base = max(self.timeout_s, RTT_FACTOR * self.slowest_s)
        return min(base * 2.0 ** (tries - 1), MAX_TIMEOUT_FACTOR * self.timeout_s)

    def asked(self, name: str) -> None:
        n = self.tries[name] = self.tries.get(name, 0) + 1
        if n > 1:
            self.retried.add(name)
        now = self.clock()
        self.asked_at[name] = now
        self.deadline[name] = now + self.wait_s(n)

    def heard(self, values: Mapping[str, ParamValue]) -> None:
        now = self.clock()
        for name in self.deadline:
            if name in values and name not in self.answered:
                self.answered.add(name)
                if self.tries[name] == 1:
                    self.slowest_s = max(self.slowest_s, now - self.asked_at[name])

    def pending(self) -> list[str]:
        """Names still waited for: unanswered, with a try left or the last one's wait running."""
        now = self.clock()
        return [n for n in self.deadline if n not in self.answered
                and (self.tries[n] < self.retries or now < self.deadline[n])]

    def due(self, now: float) -> list[str]:
        """Unanswered names whose try timed out and that have a try left."""
        return [n for n, t in self.deadline.items() if n not in self.answered
                and now >= t and self.tries[n] < self.retries]

    def next_deadline(self) -> float:
        return min(t for n, t in self.deadline.items() if n not in self.answered
                   and (self.tries[n] < self.retries or self.clock() < t))


class ParamReader:
    """Reads named parameters of ``(target_system, target_component)`` over ``link`` (a
    :class:`~companion.link.MavlinkLink` or anything with ``mav`` and ``send``/``has_peer``).
    Call :meth:`on_param_value` for every PARAM_VALUE received; :meth:`read` sends the
    requests and waits for the answers."""

    def __init__(self, link: Any, target_system: int, target_component: int) -> None:
        self.link = link
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self._values: dict[str, ParamValue] = {}
        self._arrived = asyncio.Event()
        self.ignored = 0  # PARAM_VALUEs from another system or with a type we cannot decode

    def on_param_value(self, fields: Mapping[str, Any], src_sysid: int, src_compid: int) -> None:
        """A PARAM_VALUE arrived (its decoded pymavlink fields and its source ids)."""
        if src_sysid != self.target_system or (
                self.target_component not in (0, src_compid)):
            self.ignored += 1
            return
        name = _name(fields.get("param_id", ""))
        try:
            value = decode_param_value(int(fields["param_type"]), float(fields["param_value"]))
        except (KeyError, TypeError, ValueError) as exc:
            self.ignored += 1
            log.warning("PARAM_VALUE %s ignored: %s", name or "?", exc)
            return
        if not name or not math.isfinite(value):
            self.ignored += 1
            return
        self._values[name] = ParamValue(name, value, int(fields["param_type"]),
                                        int(fields.get("param_index", -1)),
                                        int(fields.get("param_count", 0)))
        self._arrived.set()

    async def read(self, names: Sequence[str], timeout_s: float = 0.5, retries: int = 3,
                   peer_timeout_s: float = 5.0,
                   clock: Callable[[], float] = time.monotonic) -> ParamReadResult:
        """Ask for ``names`` and return what came back, the way a ground station does (module
        docstring, "Retries"): every name has its own deadline and is asked again alone when
        it passes, up to ``retries`` times in all; the wait for a try is ``timeout_s`` or
        :data:`RTT_FACTOR` times the slowest answer seen so far if longer, doubled on every
        retry of that name (at most :data:`MAX_TIMEOUT_FACTOR` x ``timeout_s``). An answer is
        taken whenever it arrives, also after the name was asked again. Waits up to
        ``peer_timeout_s`` for the autopilot to be heard first (a ``udpin`` link cannot send
        before); without a peer every name is missing."""
        for n in names:
            if not 0 < len(n) <= 16:
                raise ValueError(f"parameter name {n!r}: must be 1..16 characters")
        if not (timeout_s > 0 and math.isfinite(timeout_s)) or retries < 1:
            raise ValueError(f"timeout_s {timeout_s!r} must be > 0 and retries {retries!r} >= 1")
        t0 = clock()
        wanted = list(dict.fromkeys(names))
        if not await self._wait_for_peer(peer_timeout_s):
            log.warning("parameters: autopilot not heard within %.1f s, nothing read",
                        peer_timeout_s)
            return ParamReadResult({}, tuple(wanted), 0, clock() - t0)
        state = _ReadState(wanted, timeout_s, retries, clock)
        for n in wanted:
            if n not in self._values:
                state.sent += self._request(n)
                state.asked(n)
        while True:
            state.heard(self._values)
            now = clock()
            for n in state.due(now):
                state.sent += self._request(n)
                state.asked(n)
            wait_s = state.next_deadline() - now if state.pending() else None
            if wait_s is None:
                break
            self._arrived.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._arrived.wait(), max(wait_s, 0.0))
        found = {n: self._values[n] for n in wanted if n in self._values}
        missing = tuple(n for n in wanted if n not in self._values)
        if state.retried:
            log.info("parameters: %d of %d asked again (%d requests; slowest answer %.2f s)",
                     len(state.retried), len(wanted), state.sent, state.slowest_s)
        return ParamReadResult(found, missing, state.sent, clock() - t0)

    async def _wait_for_peer(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not getattr(self.link, "has_peer", True):
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(0.02)
        return True

    def _request(self, name: str) -> int:
        msg = self.link.mav.param_request_read_encode(
            self.target_system, self.target_component, name.encode("ascii"), -1)
        try:
            self.link.send(msg)
        except (NoPeerError, LinkError) as exc:
            log.warning("PARAM_REQUEST_READ %s not sent: %s", name, exc)
            return 0
        return 1
