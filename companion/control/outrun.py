"""Saying when the target outruns the controller's configured bounds.

A controller bounded to ``|v| <= eta_max`` cannot follow a target faster than that, nor turn
with one turning faster than its yaw-rate bound, nor hold a target accelerating (or, on a
curve, turning at speed: ``a = v omega``) harder than its acceleration bound. Nothing in the
solver says so: it just falls behind (recovery, fallback, the target leaves the view). This
check compares the target's estimated motion (what the pipeline already has:
FOLLOW_TARGET's velocity, acceleration and yaw rate, or the image estimator's velocity) with
the configured bounds and names the key to change (docs/guides/vehicle-limits.md):

=============  ==============================  ==========================================
quantity       bound                           key
=============  ==============================  ==========================================
speed          ``min(eta_max[4], eta_max[5])`` ``rmpc.eta_max[4]``, ``rmpc.eta_max[5]``
turn rate      ``u_max[3]``                    ``rmpc.u_max[3]``
acceleration   ``min(u_max[0], u_max[1])``     ``rmpc.u_max[0]``, ``rmpc.u_max[1]``
=============  ==============================  ==========================================

Hysteresis: a quantity is *outrun* once it has stayed above its bound for
:data:`ENTER_S`; it is *clear* again once it has stayed below :data:`CLEAR_FRACTION` of the
bound for :data:`CLEAR_S` (a target hovering at the bound does not flap).
:class:`OutrunCheck` is pure; :class:`OutrunMonitor` is the runtime's glue (log records).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "CLEAR_FRACTION",
    "CLEAR_S",
    "ENTER_S",
    "TOPIC_OUTRUN",
    "OutrunCheck",
    "OutrunEvent",
    "OutrunMonitor",
]

ENTER_S = 0.5
CLEAR_S = 1.0
CLEAR_FRACTION = 0.95
TOPIC_OUTRUN = "/control/outrun"
log = logging.getLogger(__name__)

#: (quantity, unit, keys to change)
QUANTITIES: tuple[tuple[str, str, str], ...] = (
    ("speed", "m/s", "rmpc.eta_max[4], rmpc.eta_max[5]"),
    ("turn rate", "rad/s", "rmpc.u_max[3]"),
    ("acceleration", "m/s^2", "rmpc.u_max[0], rmpc.u_max[1]"),
)


@dataclass(frozen=True)
class OutrunEvent:
    """A change of verdict for one quantity: ``outrun`` True (entered) or False (cleared)."""

    t_s: float
    quantity: str
    outrun: bool
    value: float
    bound: float
    unit: str
    keys: str

    def message(self) -> str:
        if self.outrun:
            return (f"the target outruns the controller: its {self.quantity} "
                    f"{self.value:.2f} {self.unit} exceeds the configured bound "
                    f"{self.bound:.2f} {self.unit}; raise {self.keys} (within the vehicle's "
                    f"limits: [vehicle_limits] from_autopilot = true builds them from the "
                    f"autopilot)")
        return (f"the target's {self.quantity} ({self.value:.2f} {self.unit}) is back within "
                f"the configured bound {self.bound:.2f} {self.unit} ({self.keys})")

    def to_record(self) -> dict[str, Any]:
        return {"t_s": self.t_s, "quantity": self.quantity, "outrun": self.outrun,
                "value": self.value, "bound": self.bound, "unit": self.unit, "keys": self.keys}


class OutrunCheck:
    """Per-quantity hysteresis (module docstring). ``bounds``: speed (m/s), turn rate (rad/s),
    acceleration (m/s^2) the configured controller can follow."""

    def __init__(self, bounds: Sequence[float]) -> None:
        if len(bounds) != len(QUANTITIES) or not all(b > 0 for b in bounds):
            raise ValueError(f"OutrunCheck: {len(QUANTITIES)} bounds > 0 expected, got {bounds}")
        self.bounds = tuple(float(b) for b in bounds)
        self.outrun = [False] * len(QUANTITIES)
        self._since: list[float | None] = [None] * len(QUANTITIES)  # candidate change since
        self.peak = [0.0] * len(QUANTITIES)  # the largest value seen

    @classmethod
    def for_bounds(cls, eta_max: Sequence[float], u_max: Sequence[float]) -> OutrunCheck:
        return cls((min(eta_max[4], eta_max[5]), u_max[3], min(u_max[0], u_max[1])))

    def update(self, t_s: float, values: Sequence[float | None]) -> list[OutrunEvent]:
        """The target's speed, turn rate and acceleration magnitudes at ``t_s`` (None or NaN:
        not known this step, the quantity's timer is held). Returns the verdicts that changed."""
        events = []
        for i, v in enumerate(values):
            if v is None or not math.isfinite(v):
                continue
            v = abs(float(v))
            self.peak[i] = max(self.peak[i], v)
            bound = self.bounds[i]
            changing = (v <= CLEAR_FRACTION * bound) if self.outrun[i] else (v > bound)
            if not changing:
                self._since[i] = None
                continue
            since = self._since[i]
            if since is None:
                self._since[i] = since = t_s
            if t_s - since >= (CLEAR_S if self.outrun[i] else ENTER_S) - 1e-9:
                self.outrun[i] = not self.outrun[i]
                self._since[i] = None
                name, unit, keys = QUANTITIES[i]
                events.append(OutrunEvent(t_s, name, self.outrun[i], v, bound, unit, keys))
        return events


def target_motion_magnitudes(velocity: Any) -> tuple[float | None, float | None, float | None]:
    """Speed, turn rate and acceleration (horizontal) of a pipeline ``VelocityEstimate``
    (None: no estimate; the image estimator gives a velocity only)."""
    if velocity is None or velocity.source == "none":
        return None, None, None
    v = np.asarray(velocity.v_a_ned_m_s, dtype=float)
    speed = float(np.hypot(v[0], v[1]))
    if velocity.source != "follow_target":
        return speed, None, None
    a = np.asarray(velocity.a_a_ned_m_s2, dtype=float)
    return speed, float(velocity.yaw_rate_rad_s), float(np.hypot(a[0], a[1]))


class OutrunMonitor:
    """The runtime's glue: one :class:`OutrunCheck` on the flown bounds (built when first
    observed: with ``[vehicle_limits] from_autopilot`` they are known only then); each change
    goes to ``/control/safety`` (WARNING when outrun) and ``/control/outrun`` (JSON)."""

    def __init__(self) -> None:
        self.check: OutrunCheck | None = None
        self.events: list[OutrunEvent] = []

    def observe(self, app: Any, res: Any, t_s: float, t_log_ns: int) -> list[OutrunEvent]:
        if self.check is None:
            self.check = OutrunCheck.for_bounds(app.cfg.rmpc.eta_max, app.cfg.rmpc.u_max)
        events = self.check.update(t_s, target_motion_magnitudes(res.target_velocity))
        records = app._records  # companion/control/recording.py: RuntimeLog
        logger = None if records is None else records.logger
        for ev in events:
            self.events.append(ev)
            log.log(logging.WARNING if ev.outrun else logging.INFO, "%s", ev.message())
            if logger is not None:
                logger.log_text("/control/safety", t_log_ns, ev.message(),
                                level="WARNING" if ev.outrun else "INFO", name="outrun")
                logger.log(TOPIC_OUTRUN, t_log_ns, ev.to_record(), schema="companion.Json")
        return events
