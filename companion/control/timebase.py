"""One time base for every input of the live process (``control.time_source``).

:class:`TimeBase` stamps frames and messages either on receipt (a real vehicle: local monotonic
time, corrected by each stream's smallest delay so a backlog keeps its true age) or with the
autopilot's own clock (the emulator, where frames carry the autopilot's boot time). The replay
(``companion/replay.py``) rebuilds the same times from the log with the same class.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

log = logging.getLogger(__name__)

# Messages whose own timestamp field (ms) is the source time in "autopilot" mode.
_STAMP_FIELDS = {
    "ATTITUDE_QUATERNION": "time_boot_ms",
    "ATTITUDE": "time_boot_ms",
    "LOCAL_POSITION_NED": "time_boot_ms",
    "ATTITUDE_TARGET": "time_boot_ms",
    "FOLLOW_TARGET": "timestamp",
    "HIGHRES_IMU": "time_usec",
}
# the stamp's unit (s per count): ms, except HIGHRES_IMU's time_usec (us since boot)
_STAMP_SCALE = {"HIGHRES_IMU": 1e-6}
STAMPED_MESSAGES = frozenset(_STAMP_FIELDS)  # the messages TimeBase reads a time from


class DelayFloor:
    """The smallest transport delay ``t_rx - t_src`` of one stream (seconds, in whatever
    offset the two clocks have), rising by at most ``drift`` s/s (clock drift), so that
    ``excess = delay - floor`` is how late one item is compared with the stream at its best.
    After ``relearn_s`` of receipt time in which every item was late by more than
    ``stale_s`` (the source clock jumped: a reboot), the floor is learnt again."""

    def __init__(self, stale_s: float, drift: float = 1e-3, relearn_s: float = 3.0) -> None:
        self.stale_s, self.drift, self.relearn_s = stale_s, drift, relearn_s
        self.floor: float | None = None
        self._t_last: float | None = None
        self._late_since: float | None = None

    def excess(self, t_rx_s: float, t_src_s: float) -> float:
        d = t_rx_s - t_src_s
        if self.floor is None or self._t_last is None:
            self.floor, self._t_last = d, t_rx_s
            return 0.0
        self.floor += self.drift * max(t_rx_s - self._t_last, 0.0)
        self._t_last = t_rx_s
        if d <= self.floor:
            self.floor, self._late_since = d, None
            return 0.0
        ex = d - self.floor
        if ex <= self.stale_s:
            self._late_since = None
        elif self._late_since is None:
            self._late_since = t_rx_s
        elif t_rx_s - self._late_since >= self.relearn_s:
            log.warning("time base: stream delays moved by %.3f s for %.1f s: relearnt", ex,
                        self.relearn_s)
            self.floor, self._late_since = d, None
            return 0.0
        return ex


class TimeBase:
    """Assigns every input a time in seconds on one base (see ``control.time_source``).

    ``receipt``: local monotonic time. A stamped input (frame ``t_us``, a message's
    ``time_boot_ms``) gets its source stamp plus its stream's smallest delay
    (:class:`DelayFloor`), i.e. when it would have arrived at best: a backlog received late
    (after a process stall, a link hiccup) keeps its true age instead of looking fresh.
    ``last_excess_s`` is how late the last input was; unstamped messages (HEARTBEAT,
    COMMAND_ACK) get their receipt time. ``autopilot``: the source's own stamps; messages
    without a stamp get the newest source time seen so far.
    """

    def __init__(self, source: str, stale_s: float = 0.25) -> None:
        self.source = source
        self.latest_s = -math.inf
        self.stale_s = stale_s
        self.last_excess_s = 0.0
        self.stale_count = 0  # stamped inputs later than stale_s (receipt mode)
        self._floors: dict[str, DelayFloor] = {}

    def _mapped(self, stream: str, t_rx_s: float, t_src_s: float) -> float:
        fl = self._floors.get(stream)
        if fl is None:
            fl = self._floors[stream] = DelayFloor(self.stale_s)
        ex = fl.excess(t_rx_s, t_src_s)
        self.last_excess_s = ex
        if ex > self.stale_s:
            self.stale_count += 1
        return t_rx_s - ex

    def message_s(self, name: str, fields: Mapping[str, Any], t_rx_ns: int) -> float:
        if self.source == "receipt":
            key = _STAMP_FIELDS.get(name)
            if key is None or key not in fields:
                self.last_excess_s = 0.0
                return t_rx_ns * 1e-9
            return self._mapped(name, t_rx_ns * 1e-9,
                                float(fields[key]) * _STAMP_SCALE.get(name, 1e-3))
        key = _STAMP_FIELDS.get(name)
        if key is not None and key in fields:
            t = float(fields[key]) * _STAMP_SCALE.get(name, 1e-3)
            self.latest_s = max(self.latest_s, t)
            return t
        return self.latest_s if math.isfinite(self.latest_s) else 0.0

    def frame_s(self, t_us: int, t_rx_ns: int) -> float:
        if self.source == "receipt":
            return self._mapped("camera", t_rx_ns * 1e-9, t_us * 1e-6)
        t = t_us * 1e-6
        self.latest_s = max(self.latest_s, t)
        return t
