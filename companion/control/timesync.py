"""The autopilot's clock on the companion's: MAVLink TIMESYNC (#111) like PX4 does it.

Pure bookkeeping with explicit times (the runtime owns the clock and the link): the companion
sends requests ``tc1 = 0, ts1 = t_local_ns``; PX4 answers ``tc1`` = its boot time (ns) at
receipt, ``ts1`` echoed. With the reply received at local ``t_rx``, one offset sample is
``offset = tc1 - (ts1 + t_rx) / 2`` (autopilot minus local, symmetric link assumed) and the
round trip ``t_rx - ts1``. The estimate is the sample with the smallest round trip among the
last ``window`` accepted ones (a long round trip means queuing, whose asymmetry biases the
sample); samples with a round trip above ``max_rtt_ns`` are dropped. PX4's own requests
(``tc1 = 0`` from the autopilot) are answered with ``tc1`` = our time, ``ts1`` echoed
(docs/wire.md, TIMESYNC).

A frame stamped ``t_us`` on the autopilot's clock (a hardware-synced camera) is then
``autopilot_now - t_us`` old; that age is what the latency compensation predicts across.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class TimesyncSample:
    offset_ns: float  # autopilot minus local
    rtt_ns: int
    t_rx_ns: int


class TimeSync:
    """Offset estimator; feed it every TIMESYNC message with :meth:`on_timesync`."""

    def __init__(self, window: int = 10, max_rtt_ns: int = 50_000_000, pending: int = 32) -> None:
        if window < 1 or max_rtt_ns <= 0 or pending < 1:
            raise ValueError("TimeSync: window >= 1, max_rtt_ns > 0, pending >= 1")
        self._samples: deque[TimesyncSample] = deque(maxlen=window)
        self._pending: deque[int] = deque(maxlen=pending)
        self._max_rtt_ns = max_rtt_ns
        self.rejected = 0

    def request(self, t_local_ns: int) -> tuple[int, int]:
        """``(tc1, ts1)`` of a request sent now."""
        self._pending.append(int(t_local_ns))
        return 0, int(t_local_ns)

    def on_timesync(self, tc1: int, ts1: int, t_rx_ns: int) -> tuple[int, int] | None:
        """Handle one TIMESYNC. Returns ``(tc1, ts1)`` to send back when it was the autopilot's
        request, else ``None`` (a reply to us: a sample, if it answers a pending request)."""
        tc1, ts1 = int(tc1), int(ts1)
        if tc1 == 0:
            return int(t_rx_ns), ts1
        if ts1 not in self._pending:
            self.rejected += 1  # not ours (or a duplicate): PX4 ignores those too
            return None
        self._pending.remove(ts1)
        rtt = int(t_rx_ns) - ts1
        if rtt < 0 or rtt > self._max_rtt_ns:
            self.rejected += 1
            return None
        self._samples.append(TimesyncSample(tc1 - (ts1 + int(t_rx_ns)) / 2.0, rtt, int(t_rx_ns)))
        return None

    @property
    def best(self) -> TimesyncSample | None:
        if not self._samples:
            return None
        return min(self._samples, key=lambda s: s.rtt_ns)

    def autopilot_s(self, t_local_ns: int) -> float | None:
        """Local time ``t_local_ns`` on the autopilot's clock (s); ``None`` before a sample."""
        b = self.best
        return None if b is None else (t_local_ns + b.offset_ns) * 1e-9


__all__ = ["TimeSync", "TimesyncSample"]
