"""``[vehicle_limits]``: whether and how the companion reads the vehicle's limits from the
autopilot (:mod:`companion.control.vehicle_limits`; docs/guides/vehicle-limits.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

from companion.core.params import checked, positive

__all__ = ["VehicleLimitsConfig"]


def _margin(x: float) -> str | None:
    return None if 0.0 <= x < 1.0 else "must be in [0, 1)"


@dataclass(frozen=True)
class VehicleLimitsConfig:
    """``[vehicle_limits]``: ``read`` the autopilot's limits on connect (log them, report a
    configured bound beyond them); ``from_autopilot``: also build the controller's bounds from
    them, each ``(1 - margin)`` times the autopilot's (module docstring); the read asks each
    parameter up to ``read_retries`` times, the first try waiting ``read_timeout_s`` (or 3 x
    the slowest answer seen, if longer) and each retry twice the one before, at most 8 x
    ``read_timeout_s`` (``companion/link/params.py``)."""

    read: bool = True
    from_autopilot: bool = False
    margin: float = field(default=0.2, metadata=checked(_margin))
    read_timeout_s: float = field(default=0.5, metadata=checked(positive))
    read_retries: int = field(default=5, metadata=checked(positive))
