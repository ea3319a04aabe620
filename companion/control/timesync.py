"""The autopilot's clock on the companion's: MAVLink TIMESYNC (#111) like PX4 does it.

Pure bookkeeping with explicit times (the runtime owns the clock and the link): the companion
sends requests ``tc1 = 0, ts1 = t_local_ns``; PX4 answers ``tc1`` = its boot time (ns) at
receipt, ``ts1`` echoed. With the reply received at local ``t_rx``, one offset sample is
``offset = tc1 - (ts1 + t_rx) / 2`` (autopilot minus local, symmetric link assumed) and the
round trip ``t_rx - ts1``. The estimate is the sample with the smallest round trip among the
last ``window`` accepted ones (a long round trip means queuing, whose asymmetry biases the
sample); samples with a round trip above ``max_rtt_ns`` are dropped. PX4's own requests
(``tc1 = 0`` from the autopilot) are answered with ``tc1`` = our time, ``ts1`` echoed
(docs/reference/wire.md, TIMESYNC).

A frame stamped ``t_us`` on the autopilot's clock (a hardware-synced camera) is then
``autopilot_now - t_us`` old; that age is what the latency compensation predicts across.
"""

from __future__ import annotations

import math
import statistics
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


class ActuationDelayMeter:
    """The actuation delay measured online (``control.latency.auto_delay``): from the step's
    "now" (the time base the command history is stamped on) to the moment the vehicle receives
    the setpoint sent in that step.

    A TIMESYNC request sent right before a setpoint travels the same way; PX4 answers it with
    ``tc1`` = its boot time when the request arrived, i.e. when the setpoint did. One sample
    is that moment on the control time base minus the step's "now":

    * ``"autopilot"`` and ``"timesync"`` (now on the autopilot's clock): ``tc1 - now``. With
      ``"autopilot"`` now is the newest telemetry stamp, so the sample holds the whole
      vehicle -> companion delay, the step's computation and the companion -> vehicle delay
      (the round trip); with ``"timesync"`` now is the mapped local clock, so it holds the
      computation and the companion -> vehicle delay only.
    * ``"receipt"`` (everything stamped on arrival): the vehicle's state at the moment the
      setpoint acts reaches us a vehicle -> companion delay later, like the reply, so the
      moment is the reply's receipt time: ``t_rx - now``, the local round trip.

    The value is the median of the last ``window`` samples (jitter-robust, a reordered or late
    reply does not move it), once ``min_samples`` are in; samples above ``max_s`` or below
    ``-tolerance_s`` are dropped and counted; small negative ones (stamp granularity) count as
    0. Pure bookkeeping: the runtime sends the probes and feeds the replies."""

    def __init__(self, time_source: str, window: int = 21, min_samples: int = 5,
                 max_s: float = 0.5, probe_interval_s: float = 0.1, pending: int = 64,
                 tolerance_s: float = 0.005) -> None:
        if time_source not in ("receipt", "autopilot", "timesync"):
            raise ValueError(f"ActuationDelayMeter: unknown time source {time_source!r}")
        if not 1 <= min_samples <= window or max_s <= 0 or probe_interval_s < 0 or pending < 1:
            raise ValueError("ActuationDelayMeter: need 1 <= min_samples <= window, max_s > 0,"
                             " probe_interval_s >= 0, pending >= 1")
        self.time_source = time_source
        self.min_samples = min_samples
        self.max_s = max_s
        self.probe_interval_s = probe_interval_s
        self.tolerance_s = tolerance_s
        self._samples: deque[float] = deque(maxlen=window)
        self._pending: dict[int, float] = {}
        self._pending_max = pending
        self._last_probe_s = -math.inf
        self.rejected = 0
        self.replies = 0
        self._value: float | None = None  # value() of the window as it is (None: not known)

    def due(self, now_s: float) -> bool:
        """A probe is due at control time ``now_s`` (at most one per ``probe_interval_s``)."""
        return now_s - self._last_probe_s >= self.probe_interval_s - 1e-9 or \
            now_s < self._last_probe_s  # the time base restarted

    def sent(self, ts1_ns: int, now_s: float) -> None:
        """A request with ``ts1 = ts1_ns`` left right before the setpoint of the step whose
        "now" is ``now_s``."""
        self._last_probe_s = now_s
        self._pending[int(ts1_ns)] = float(now_s)
        while len(self._pending) > self._pending_max:  # lost replies: forget the oldest
            del self._pending[next(iter(self._pending))]

    def on_reply(self, tc1_ns: int, ts1_ns: int, t_rx_ns: int) -> float | None:
        """PX4's answer (``tc1 > 0``) to one of our probes: the sample (s) it gave, or
        ``None`` (not a probe of ours, a duplicate, or out of bounds)."""
        if int(tc1_ns) <= 0:  # the autopilot's own request
            return None
        now_s = self._pending.pop(int(ts1_ns), None)
        if now_s is None:
            return None
        self.replies += 1
        t_eff = int(t_rx_ns) * 1e-9 if self.time_source == "receipt" else int(tc1_ns) * 1e-9
        d = t_eff - now_s
        if not math.isfinite(d) or d > self.max_s or d < -self.tolerance_s:
            self.rejected += 1
            return None
        d = max(d, 0.0)
        self._samples.append(d)
        self._value = None  # the window moved: the median again on the next value()
        return d

    @property
    def samples(self) -> int:
        return len(self._samples)

    def value(self) -> float | None:
        """The measured delay (s), ``None`` until ``min_samples`` are in."""
        if len(self._samples) < self.min_samples:
            return None
        if self._value is None:  # every step asks; the window moves ~once in two steps
            self._value = float(statistics.median(self._samples))
        return self._value

    def spread(self) -> float | None:
        """Max minus min of the window (s): the jitter the median smooths out."""
        if len(self._samples) < self.min_samples:
            return None
        return max(self._samples) - min(self._samples)


__all__ = ["ActuationDelayMeter", "TimeSync", "TimesyncSample"]
