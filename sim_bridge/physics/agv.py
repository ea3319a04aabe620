"""The ground vehicle (AGV): analytic trajectories with exact first and second derivatives.

Pure math (numpy only). World frame NED; the AGV's position is the centre of its top, at the
constant NED height ``top_z_m``. Its heading ``yaw_rad`` is the direction of its path's tangent
(the AGV frame: x forward along the path, y right, z down).

Kinds (``tau = speed_scale * t`` is the path time; velocity scales with ``speed_scale``,
acceleration with ``speed_scale**2``, yaw rate with ``speed_scale``):

- ``paper``: Yang & Li 2024, spec section 8: ``x = 0.1 tau``, ``y = 4 sin(0.025 tau)``,
  ``yaw = atan2(ydot, xdot)`` (pi/4 at t = 0), period 251.3 s.
- ``line``: straight north at 0.3 m/s, yaw 0.
- ``circle``: radius 3 m at 0.3 m/s, starting at the origin heading north, turning right
  (clockwise seen from above, yaw increasing).
- ``figure8``: ``x = 3 sin(w tau)``, ``y = 1.5 sin(2 w tau)`` with ``w = 2 pi / 60`` s: a figure
  eight through the origin; the speed never vanishes.
- ``stop_and_go``: along the path ``x = sigma``, ``y = sin(0.2 sigma)``; the progress ``sigma``
  moves for 8 s with the smooth speed profile ``0.25 (1 - cos(2 pi tau'/8))`` m/s (zero speed and
  zero acceleration at both ends), then stops for 4 s, and repeats. The heading is the path's
  tangent, so while stopped the AGV keeps the last yaw.
- ``ramp``: straight north from rest, accelerating at ``ramp_accel_m_s2`` (default 1.0 m/s^2)
  up to the cruise speed ``0.3 speed_scale`` m/s, then cruising (yaw 0). Unlike the other kinds
  ``speed_scale`` sets only the cruise speed: the acceleration is ``ramp_accel_m_s2`` whatever
  the scale (``speed_scale = 10``: 3 m/s, reached after 3 s and 4.5 m).

Every kind starts at the origin (``[0, 0, top_z_m]`` at ``t = 0``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_bridge import ConfigError

__all__ = ["KINDS", "AgvState", "AgvTrajectory"]

KINDS = ("paper", "line", "circle", "figure8", "stop_and_go", "ramp")

# Path parameters (metres, seconds). Kept here, with the docstring above, as the definition.
_PAPER_VX_M_S = 0.1
_PAPER_AMP_M = 4.0
_PAPER_W_RAD_S = 0.025
_LINE_SPEED_M_S = 0.3
_CIRCLE_RADIUS_M = 3.0
_CIRCLE_SPEED_M_S = 0.3
_FIG8_AX_M = 3.0
_FIG8_AY_M = 1.5
_FIG8_W_RAD_S = 2.0 * math.pi / 60.0
_SG_GO_S = 8.0
_SG_STOP_S = 4.0
_SG_VMAX_M_S = 0.5  # peak progress speed (m/s), reached mid-way through the go phase
_SG_AMP_M = 1.0
_SG_K_RAD_M = 0.2
_RAMP_CRUISE_M_S = 0.3  # at speed scale 1


def _vec3(x: Any, name: str) -> np.ndarray:
    a = np.array(x, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise ConfigError(f"AgvState.{name}: must have 3 components, got shape {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class AgvState:
    """The AGV at time ``t_s``: centre of its top, NED (m, m/s, m/s^2), heading (rad, rad/s)."""

    t_s: float
    pos_ned_m: np.ndarray
    vel_ned_m_s: np.ndarray
    acc_ned_m_s2: np.ndarray
    yaw_rad: float
    yaw_rate_rad_s: float

    def __post_init__(self) -> None:
        for name in ("pos_ned_m", "vel_ned_m_s", "acc_ned_m_s2"):
            object.__setattr__(self, name, _vec3(getattr(self, name), name))
        object.__setattr__(self, "t_s", float(self.t_s))
        object.__setattr__(self, "yaw_rad", float(self.yaw_rad))
        object.__setattr__(self, "yaw_rate_rad_s", float(self.yaw_rate_rad_s))


def _heading(xd: float, yd: float, xdd: float, ydd: float) -> tuple[float, float]:
    """Yaw of the tangent ``(xd, yd)`` and its rate ``(xd ydd - yd xdd) / (xd^2 + yd^2)``."""
    v2 = xd * xd + yd * yd
    return math.atan2(yd, xd), (xd * ydd - yd * xdd) / v2


class AgvTrajectory:
    """An analytic AGV path: :meth:`state` gives position, velocity, acceleration and heading.

    ``kind`` is one of :data:`KINDS`; ``speed_scale`` (> 0) scales time along the path;
    ``top_z_m`` is the NED z of the AGV top (constant); ``ramp_accel_m_s2`` the ``ramp``
    kind's acceleration (> 0).
    """

    def __init__(self, kind: str, speed_scale: float = 1.0, top_z_m: float = 0.0,
                 ramp_accel_m_s2: float = 1.0) -> None:
        if kind not in KINDS:
            raise ConfigError(
                f"sim.agv.trajectory: must be one of {', '.join(KINDS)}, got {kind!r}"
            )
        if not (math.isfinite(speed_scale) and speed_scale > 0):
            raise ConfigError(
                f"sim.agv.speed_scale: must be a finite number > 0, got {speed_scale}"
            )
        if not math.isfinite(top_z_m):
            raise ConfigError(f"sim.agv.top_z_m: must be finite, got {top_z_m}")
        if not (math.isfinite(ramp_accel_m_s2) and ramp_accel_m_s2 > 0):
            raise ConfigError(
                f"sim.agv.ramp_accel_m_s2: must be a finite number > 0, got {ramp_accel_m_s2}"
            )
        self.kind = kind
        self.ramp_accel_m_s2 = float(ramp_accel_m_s2)
        self.speed_scale = float(speed_scale)
        self.top_z_m = float(top_z_m)
        self._planar = {
            "paper": self._paper,
            "line": self._line,
            "circle": self._circle,
            "figure8": self._figure8,
            "stop_and_go": self._stop_and_go,
            "ramp": self._line,  # not used: state() computes the ramp in real time
        }[kind]

    def state(self, t_s: float) -> AgvState:
        """The AGV at time ``t_s`` (s since the start)."""
        s = self.speed_scale
        if self.kind == "ramp":
            return self._ramp(float(t_s))
        x, y, xd, yd, xdd, ydd, yaw, yaw_rate = self._planar(s * float(t_s))
        return AgvState(
            t_s=t_s,
            pos_ned_m=np.array([x, y, self.top_z_m]),
            vel_ned_m_s=np.array([s * xd, s * yd, 0.0]),
            acc_ned_m_s2=np.array([s * s * xdd, s * s * ydd, 0.0]),
            yaw_rad=yaw,
            yaw_rate_rad_s=s * yaw_rate,
        )

    def _ramp(self, t_s: float) -> AgvState:
        """Straight north: constant acceleration from rest to the cruise speed, then cruise
        (the acceleration steps at both ends, as a vehicle's speed controller at its limit)."""
        a, v_c = self.ramp_accel_m_s2, _RAMP_CRUISE_M_S * self.speed_scale
        t = max(t_s, 0.0)
        t_c = v_c / a
        if t < t_c:
            x, v, acc = 0.5 * a * t * t, a * t, a
        else:
            x, v, acc = 0.5 * a * t_c * t_c + v_c * (t - t_c), v_c, 0.0
        return AgvState(t_s=t_s, pos_ned_m=np.array([x, 0.0, self.top_z_m]),
                        vel_ned_m_s=np.array([v, 0.0, 0.0]),
                        acc_ned_m_s2=np.array([acc, 0.0, 0.0]), yaw_rad=0.0, yaw_rate_rad_s=0.0)

    # Each planar path returns (x, y, dx, dy, ddx, ddy, yaw, dyaw) in path time tau.
    @staticmethod
    def _paper(tau: float) -> tuple[float, ...]:
        w, a = _PAPER_W_RAD_S, _PAPER_AMP_M
        x, xd, xdd = _PAPER_VX_M_S * tau, _PAPER_VX_M_S, 0.0
        y = a * math.sin(w * tau)
        yd = a * w * math.cos(w * tau)
        ydd = -a * w * w * math.sin(w * tau)
        return (x, y, xd, yd, xdd, ydd, *_heading(xd, yd, xdd, ydd))

    @staticmethod
    def _line(tau: float) -> tuple[float, ...]:
        v = _LINE_SPEED_M_S
        return (v * tau, 0.0, v, 0.0, 0.0, 0.0, 0.0, 0.0)

    @staticmethod
    def _circle(tau: float) -> tuple[float, ...]:
        r, w = _CIRCLE_RADIUS_M, _CIRCLE_SPEED_M_S / _CIRCLE_RADIUS_M
        c, s = math.cos(w * tau), math.sin(w * tau)
        x, y = r * s, r * (1.0 - c)
        xd, yd = r * w * c, r * w * s
        xdd, ydd = -r * w * w * s, r * w * w * c
        return (x, y, xd, yd, xdd, ydd, *_heading(xd, yd, xdd, ydd))

    @staticmethod
    def _figure8(tau: float) -> tuple[float, ...]:
        ax, ay, w = _FIG8_AX_M, _FIG8_AY_M, _FIG8_W_RAD_S
        x, y = ax * math.sin(w * tau), ay * math.sin(2 * w * tau)
        xd, yd = ax * w * math.cos(w * tau), 2 * ay * w * math.cos(2 * w * tau)
        xdd, ydd = -ax * w * w * math.sin(w * tau), -4 * ay * w * w * math.sin(2 * w * tau)
        return (x, y, xd, yd, xdd, ydd, *_heading(xd, yd, xdd, ydd))

    @staticmethod
    def _stop_and_go(tau: float) -> tuple[float, ...]:
        # Progress sigma(tau): per period, a go phase with speed vmax/2 (1 - cos(2 pi tau'/T_go))
        # (smooth start and stop), then a stop phase. Distance per period: vmax/2 * T_go.
        period = _SG_GO_S + _SG_STOP_S
        n = math.floor(tau / period)
        tp = tau - n * period
        per = 0.5 * _SG_VMAX_M_S * _SG_GO_S
        if tp < _SG_GO_S:
            ph = 2.0 * math.pi * tp / _SG_GO_S
            sig = n * per + 0.5 * _SG_VMAX_M_S * (tp - _SG_GO_S / (2.0 * math.pi) * math.sin(ph))
            sd = 0.5 * _SG_VMAX_M_S * (1.0 - math.cos(ph))
            sdd = 0.5 * _SG_VMAX_M_S * (2.0 * math.pi / _SG_GO_S) * math.sin(ph)
        else:
            sig, sd, sdd = (n + 1) * per, 0.0, 0.0
        # Path p(sigma) = (sigma, A sin(k sigma)) and its sigma-derivatives.
        a, k = _SG_AMP_M, _SG_K_RAD_M
        px, py = sig, a * math.sin(k * sig)
        p1x, p1y = 1.0, a * k * math.cos(k * sig)
        p2x, p2y = 0.0, -a * k * k * math.sin(k * sig)
        yaw, curv_rate = _heading(p1x, p1y, p2x, p2y)  # d yaw / d sigma
        return (
            px,
            py,
            p1x * sd,
            p1y * sd,
            p2x * sd * sd + p1x * sdd,
            p2y * sd * sd + p1y * sdd,
            yaw,
            curv_rate * sd,
        )
