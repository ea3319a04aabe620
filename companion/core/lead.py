"""Lead compensation of the vehicle's tilt lag (docs/reference/estimator.md, "Tilt-lag lead").

The RMPC's model (spec 4) takes the commanded acceleration as the vehicle's acceleration. A
real multicopter reaches a commanded tilt, and so a horizontal acceleration, only through its
attitude and rate loops: close to a first-order lag ``a' = (c - a) / tau`` (PX4's defaults:
10-90 % roll-step rise ~215 ms, ``tau`` ~0.1 s). The exact inverse of that lag for a desired
acceleration ``a_d(t)`` is the command ``c = a_d + tau a_d'``: sent instead of ``a_d``, the
lagged vehicle flies ``a_d`` after the transient, so the model holds again and a disturbance
estimate acts at once instead of ``tau`` later.

Here ``a_d`` is the horizontal specific force the setpoint mapping asks for (the controller's
input minus the estimated disturbance, NED) at the control steps, and ``a_d'`` its backward
difference. Only the horizontal (tilt) part is led: the vertical acceleration follows the
thrust through the motors, much faster. The lead term is bounded in norm (``max_m_s2``,
default 0.3 m/s^2: a fifth of the paper's input bound) and starts afresh after a gap, a level
hover, or while PX4 flies the vehicle itself (before OFFBOARD), so a jump in the command never
becomes a kick larger than the bound. It is a small-signal correction: the lead terms of
disturbance rejection are hundredths of m/s^2. The pipeline leads only the nominal tracking
(the hard problem, or a controller without a soft copy): a recovery's chase of a target that got
away, led, pushed corners further out in near-edge starts (docs/reference/estimator.md, "Tilt-lag
lead").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from companion.core.errors import ParamError


@dataclass(frozen=True)
class LeadParams:
    """``[control.lead]``: ``enabled``; ``attitude_lag_s``: the vehicle's tilt response time
    constant (first-order equivalent; ``companion log lag`` measures it from a flight log);
    ``max_m_s2``: bound on the norm of the lead term (m/s^2); ``max_gap_s``: a longer interval
    between two commands starts the difference afresh (no lead on that step)."""

    enabled: bool = True
    attitude_lag_s: float = 0.1
    max_m_s2: float = 0.3
    max_gap_s: float = 0.15

    def __post_init__(self) -> None:
        if not (math.isfinite(self.attitude_lag_s) and 0.0 <= self.attitude_lag_s <= 1.0):
            raise ParamError("control.lead.attitude_lag_s: must be in [0, 1] s "
                             f"(got {self.attitude_lag_s!r})")
        if not (math.isfinite(self.max_m_s2) and self.max_m_s2 >= 0.0):
            raise ParamError(f"control.lead.max_m_s2: must be >= 0 (got {self.max_m_s2!r})")
        if not (math.isfinite(self.max_gap_s) and self.max_gap_s > 0.0):
            raise ParamError(f"control.lead.max_gap_s: must be > 0 (got {self.max_gap_s!r})")


@dataclass
class TiltLead:
    """The lead filter: ``apply(t_s, a_ned_h)`` once per command sent, ``reset()`` when a
    command is not the controller's (level hover, nothing sent, PX4 flying itself)."""

    params: LeadParams
    _prev: tuple[float, tuple[float, float]] | None = field(init=False, default=None)

    def reset(self) -> None:
        self._prev = None

    def apply(self, t_s: float, a_ned_h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``(command, lead term)``, both (2,) NED m/s^2, for the desired horizontal specific
        force ``a_ned_h`` at ``t_s``. Non-finite input raises ``ValueError`` (and resets)."""
        if isinstance(a_ned_h, tuple) and len(a_ned_h) == 2:
            ax, ay = float(a_ned_h[0]), float(a_ned_h[1])  # the control step's path
        else:
            a = np.asarray(a_ned_h, dtype=float).reshape(-1)
            if a.shape != (2,):
                self._prev = None
                raise ValueError(f"tilt lead: malformed input {a.tolist()} at {t_s!r}")
            ax, ay = a.tolist()
        if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(float(t_s))):
            self._prev = None
            raise ValueError(f"tilt lead: non-finite or malformed input {[ax, ay]} at {t_s!r}")
        prev, self._prev = self._prev, (float(t_s), (ax, ay))
        p = self.params
        if not p.enabled or p.attitude_lag_s <= 0.0 or prev is None:
            return np.array([ax, ay]), np.zeros(2)
        dt = float(t_s) - prev[0]
        if not 0.0 < dt <= p.max_gap_s:
            return np.array([ax, ay]), np.zeros(2)
        # plain floats, numpy's formulas: lag (a - prev) / dt, its norm, the bound
        lx = p.attitude_lag_s * (ax - prev[1][0]) / dt
        ly = p.attitude_lag_s * (ay - prev[1][1]) / dt
        n = math.sqrt(lx * lx + ly * ly)
        if n > p.max_m_s2:
            k = p.max_m_s2 / n
            lx, ly = lx * k, ly * k
        return np.array([ax + lx, ay + ly]), np.array([lx, ly])


__all__ = ["LeadParams", "TiltLead"]
