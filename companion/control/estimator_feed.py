"""What the disturbance estimator is fed each step: velocity (and accelerometer) samples with
the thrust that flew over each interval and the body axis it pushed along.

The thrust is ours while our setpoints fly the vehicle (from the pipeline's command history),
the autopilot's reported one before (``control.estimator.autopilot_thrust``), unknown
otherwise (the sample then only advances the filter's time).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from companion.config import Config
from companion.control.telemetry import TelemetryStore
from companion.core.disturbance import DisturbanceEstimator
from companion.core.geometry import body_z_from_quat, rotation_from_quat

PX4_MAIN_OFFBOARD = 6  # PX4 custom main mode (companion/link/px4.py; core-side copy)


class EstimatorFeed:
    """Feeds ``dist`` from the telemetry store; ``commands``: the pipeline's command history
    ``(t_effect_s, u (4,), thrust_norm)`` in time order (shared, read only here)."""

    def __init__(self, cfg: Config, dist: DisturbanceEstimator,
                 commands: deque[tuple[float, np.ndarray, float]]) -> None:
        self.cfg = cfg
        self._dist = dist
        self._commands = commands
        self._control_since: float | None = None  # since when our setpoints fly the vehicle

    def update(self, store: TelemetryStore, in_control: bool | None, t_now: float) -> None:
        """Feed every velocity sample newer than the filter's with the thrust commanded over
        the interval (time-weighted) and the body z axis measured at its middle. While PX4 is
        in OFFBOARD and armed that is our thrust; before (armed, in the air, PX4's own mode)
        the autopilot's thrust setpoint from ATTITUDE_TARGET, when it streams one. With the
        accelerometer (``control.estimator.accelerometer``), the HIGHRES_IMU samples newer
        than the filter and not newer than the newest velocity sample go in between, in time
        order (each with the attitude at its own time)."""
        f = self._dist
        mode = store.mode
        ours = mode is not None and mode.armed and mode.main_mode == PX4_MAIN_OFFBOARD
        if in_control is not None:
            ours = in_control
        if not ours:
            self._control_since = None
        elif self._control_since is None:
            # our setpoints fly the vehicle from the next one on: an interval that began
            # earlier was flown by PX4's own controller and says nothing about our thrust
            self._control_since = t_now
        since = self._control_since
        own = self.cfg.control.estimator.autopilot_thrust and mode is not None and mode.armed
        events = _newer_kinematics(store, f.t_s)
        if f.params.accelerometer and events and store.accel:
            newest_v = events[-1][0]
            events += [(a.t_s, 1, a) for a in store.accel
                       if (f.t_s is None or a.t_s > f.t_s) and a.t_s <= newest_v]
            events.sort(key=lambda e: (e[0], e[1]))
        for t_s, kind, sample in events:
            # (a velocity sample goes before an accelerometer sample of the same instant)
            if f.t_s is not None and (t_s < f.t_s or (kind == 0 and t_s == f.t_s)):
                continue
            thrust, body_z = self._inputs_over(f.t_s, t_s, store, since, own)
            if kind == 0:
                f.update(t_s, sample.vel_ned_m_s, thrust, body_z)
                continue
            a = store.attitude_at(t_s)
            if a is None:
                continue
            rot = rotation_from_quat(np.array(a.q_wxyz))
            f.update_accel(t_s, sample.f_frd_m_s2[:2], thrust, body_z, rot)

    def _inputs_over(self, t0: float | None, t1: float, store: TelemetryStore,
                     since: float | None, own: bool
                     ) -> tuple[float | None, tuple[float, float, float] | None]:
        """The thrust that flew over ``[t0, t1]`` (ours while in control, the autopilot's
        before) and the body z axis at its middle; ``(None, None)`` when unknown."""
        if t0 is None:
            return None, None
        thrust = None
        if since is not None and t0 >= since - 1e-9:
            thrust = self._thrust_over(t0, t1)
        elif own and (since is None or t1 <= since + 1e-9):
            # PX4's own modes fly the vehicle (e.g. the pre-flight stream before OFFBOARD):
            # the thrust it reports is the one flying, so the hover thrust is estimated before
            # our first command is flown
            thrust = store.autopilot_thrust_over(
                t0, t1, self.cfg.control.estimator.autopilot_thrust_max_age_s)
        if thrust is None:
            return None, None
        a = store.attitude_at(0.5 * (t0 + t1))
        if a is None:
            return None, None
        return thrust, body_z_from_quat(a.q_wxyz)

    def _thrust_over(self, t0: float, t1: float) -> float | None:
        """Time-weighted thrust commanded over ``[t0, t1]``; ``None`` if nothing was in force
        at ``t0``."""
        cmds = self._commands
        if not cmds or cmds[0][0] > t0 + 1e-9 or t1 <= t0:
            return None
        # a command that ends by t0 adds nothing: start at the newest one in force at t0,
        # found from the newest back (the history is in time order), and stop at the first
        # taking effect at or after t1: the same additions in the same order as a walk over
        # the whole history, so the same bits
        n = len(cmds)
        i = n - 1
        while i > 0 and cmds[i][0] > t0:
            i -= 1
        total = 0.0
        while i < n:
            te, _, thr = cmds[i]
            if te >= t1:
                break
            end = cmds[i + 1][0] if i + 1 < n else math.inf
            lo, hi = max(te, t0), min(end, t1)
            if hi > lo:
                total += thr * (hi - lo)
            i += 1
        return total / (t1 - t0)


def _newer_kinematics(store: TelemetryStore, t_s: float | None) -> list[tuple[float, int, Any]]:
    """The velocity samples newer than the filter's time ``t_s`` (all when ``None``), oldest
    first, as ``(t_s, 0, sample)`` events. The store keeps them in time order (it rejects
    an older one), so the walk goes from the newest back and stops at the filter's time."""
    hist = store.kinematics_history
    if t_s is None:
        return [(k.t_s, 0, k) for k in hist]
    out: list[tuple[float, int, Any]] = []
    for k in reversed(hist):
        if not k.t_s > t_s:
            break
        out.append((k.t_s, 0, k))
    out.reverse()
    return out
