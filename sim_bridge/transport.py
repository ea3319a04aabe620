"""The autopilot -> client transport delay of the vehicle's MAVLink links (``[sim.telemetry]``
``delay_ms`` +- ``delay_jitter_ms``, uniform, in order): messages wait in a delay line per link
until they are due, in lockstep at their due time in simulated time (docs/reference/wire.md)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from sim_bridge.delay import DelayLine, rngs
from sim_bridge.link import Address, MavUdpLink


class Transport:
    """The transport delay of every vehicle link (``delay_s`` +- ``jitter_s``); ``now_s`` is the
    runtime's boot-time clock."""

    def __init__(self, delay_s: float, jitter_s: float, seed: int, *, lockstep: bool,
                 now_s: Callable[[], float]) -> None:
        self.delay_s, self.jitter_s = delay_s, jitter_s
        self.lockstep = lockstep
        self._now_s = now_s
        (self._rng,) = rngs(seed, 1, salt=3)
        self._lines: dict[str, DelayLine[tuple[list[bytes], Address | None]]] = {}
        self._links: dict[str, MavUdpLink] = {}

    def add(self, link: MavUdpLink) -> None:
        """Route ``link``'s delayed messages through a delay line of its own."""
        self._links[link.name] = link
        self._lines[link.name] = DelayLine()

    def tx(self, link: MavUdpLink, msg: Any, addr: Address | None = None, *,
           reply: bool = False, rng: np.random.Generator | None = None) -> None:
        """Send ``msg`` on a vehicle link, through the transport delay (``sim.telemetry``).
        In lockstep a ``reply`` (ACK, requested message, TIMESYNC/PING answer) is not delayed:
        simulated time stands still while the step waits."""
        if self.delay_s <= 0 or (reply and self.lockstep):
            link.send(msg, addr)
            return
        d = self.delay_s + self.jitter_s * float((rng or self._rng).uniform(-1.0, 1.0))
        self._lines[link.name].push(self._now_s() + max(0.0, d), (link.pack(msg), addr))

    def flush(self, now_s: float) -> None:
        """Send every delayed message due by ``now_s``."""
        for name, line in self._lines.items():
            link = self._links[name]
            for frames, addr in line.pop_due(now_s):
                link.send_frames(frames, addr)

    def next_due_s(self) -> float:
        return min((line.next_due_s for line in self._lines.values()), default=math.inf)
