"""What the companion knows about the vehicle and the target, with the time it learnt it.

Fed with decoded MAVLink messages as ``(name, fields, t_s)``: ``fields`` is the message's field
dict (live :func:`companion.link.message_fields`, decoded once by the link; in replay
pymavlink's ``to_dict()`` of the logged frame: the same values), ``t_s`` the message's time on
the companion's time base (see :class:`companion.control.timebase.TimeBase`). The same store
serves the live process and the replay, so both compute identical commands from identical inputs.

Pure bookkeeping: no sockets, no clocks.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from companion.core.frozen import make
from companion.core.geometry import euler_zyx_from_quat, quat_from_euler_zyx

EARTH_RADIUS_M = 6378137.0


@dataclass(frozen=True)
class AttitudeSample:
    t_s: float
    q_wxyz: tuple[float, float, float, float]  # FRD body relative to NED
    yaw_rate_rad_s: float


@dataclass(frozen=True)
class KinematicsSample:
    t_s: float
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]


@dataclass(frozen=True)
class TargetSample:
    """The AGV's own state from FOLLOW_TARGET, in the shared local NED frame."""

    t_s: float
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    acc_ned_m_s2: tuple[float, float, float]
    yaw_rad: float
    yaw_rate_rad_s: float


@dataclass(frozen=True)
class ThrustSample:
    """The autopilot's own collective-thrust setpoint (ATTITUDE_TARGET ``thrust``, 0..1)."""

    t_s: float
    thrust_norm: float


@dataclass(frozen=True)
class AccelSample:
    """The accelerometer of HIGHRES_IMU: specific force in body FRD (m/s^2), bias-corrected by
    the autopilot's estimator (PX4: vehicle_imu's delta velocity over its interval less EKF2's
    accelerometer bias), ``t_s`` its sample time (``time_usec``)."""

    t_s: float
    f_frd_m_s2: tuple[float, float, float]


#: a specific force beyond this (m/s^2, any axis) is not a flying multicopter's
ACCEL_PLAUSIBLE_M_S2 = 160.0


@dataclass(frozen=True)
class VehicleMode:
    t_s: float
    armed: bool
    main_mode: int
    sub_mode: int


class TelemetryStore:
    """Latest samples per kind; attitude keeps a short history for interpolation."""

    #: the only messages :meth:`ingest` takes (any other returns False and changes nothing)
    MESSAGES = frozenset({"FOLLOW_TARGET", "ATTITUDE_QUATERNION", "ATTITUDE",
                          "LOCAL_POSITION_NED", "HEARTBEAT", "ATTITUDE_TARGET",
                          "EXTENDED_SYS_STATE", "HIGHRES_IMU"})

    def __init__(
        self,
        target_sysid: int,
        origin_lat_deg: float,
        origin_lon_deg: float,
        origin_alt_m: float,
        history: int = 64,
        autopilot_sysid: int | None = None,
    ) -> None:
        self._target_sysid = target_sysid
        self._autopilot_sysid = autopilot_sysid
        self._origin = (origin_lat_deg, origin_lon_deg, origin_alt_m)
        self.attitude: deque[AttitudeSample] = deque(maxlen=history)
        self.kinematics: KinematicsSample | None = None
        self.kinematics_history: deque[KinematicsSample] = deque(maxlen=history)
        self.target: TargetSample | None = None
        self.mode: VehicleMode | None = None
        # the autopilot's thrust setpoint (PX4 streams ATTITUDE_TARGET at 10 Hz on an onboard
        # link) and its landed state (EXTENDED_SYS_STATE: 2 = in air)
        self.thrust_setpoints: deque[ThrustSample] = deque(maxlen=history)
        self.landed_state: int | None = None
        # the accelerometer (HIGHRES_IMU, 50 Hz on an onboard link), only when asked for
        self.accel: deque[AccelSample] = deque(maxlen=history)
        self.rejected: dict[str, int] = {}

    # -- ingest -----------------------------------------------------------------------------

    def ingest(self, name: str, fields: Mapping[str, Any], t_s: float, src_sysid: int) -> bool:
        """Take one message; returns False (and counts why) when it is not usable."""
        try:
            if name == "FOLLOW_TARGET":
                if src_sysid != self._target_sysid:
                    return self._reject("FOLLOW_TARGET from unexpected sysid")
                return self._follow_target(fields, t_s)
            if name == "ATTITUDE_QUATERNION":  # (50-100 Hz: written out, no helper calls)
                q1, q2, q3, q4 = (float(fields["q1"]), float(fields["q2"]),
                                  float(fields["q3"]), float(fields["q4"]))
                rate = float(fields["yawspeed"])
                isfinite = math.isfinite
                # _norm's sum in its order (from 0: the same value)
                if not (isfinite(q1) and isfinite(q2) and isfinite(q3) and isfinite(q4)
                        and isfinite(rate)) or abs(
                            math.sqrt(q1 * q1 + q2 * q2 + q3 * q3 + q4 * q4) - 1.0) > 1e-3:
                    return self._reject("ATTITUDE_QUATERNION not a unit quaternion")
                return self._push_attitude(name, make(AttitudeSample, t_s=t_s,
                                                      q_wxyz=(q1, q2, q3, q4),
                                                      yaw_rate_rad_s=rate))
            if name == "ATTITUDE":  # PX4 onboard: 100 Hz against ATTITUDE_QUATERNION's 50 Hz
                roll, pitch, yaw = (float(fields["roll"]), float(fields["pitch"]),
                                    float(fields["yaw"]))
                rate = float(fields["yawspeed"])
                if not _finite(roll, pitch, yaw, rate):
                    return self._reject("ATTITUDE non-finite")
                # (the quaternion's floats by tolist: the values float() gave one by one)
                w, x, y, z = quat_from_euler_zyx(roll, pitch, yaw).tolist()
                return self._push_attitude(name, make(AttitudeSample, t_s=t_s,
                                                      q_wxyz=(w, x, y, z),
                                                      yaw_rate_rad_s=rate))
            if name == "LOCAL_POSITION_NED":
                pos = (float(fields["x"]), float(fields["y"]), float(fields["z"]))
                vel = (float(fields["vx"]), float(fields["vy"]), float(fields["vz"]))
                if not _finite(*pos, *vel):
                    return self._reject("LOCAL_POSITION_NED non-finite")
                k = make(KinematicsSample, t_s=t_s, pos_ned_m=pos, vel_ned_m_s=vel)
                if self.kinematics is not None and t_s < self.kinematics.t_s:
                    return self._reject("LOCAL_POSITION_NED out of order")
                self.kinematics = k
                self.kinematics_history.append(k)
                return True
            if name == "HIGHRES_IMU":
                if self._autopilot_sysid is not None and src_sysid != self._autopilot_sysid:
                    return self._reject("HIGHRES_IMU not from the autopilot")
                if not int(fields.get("fields_updated", 0b111)) & 0b111:
                    return self._reject("HIGHRES_IMU without an accelerometer update")
                acc = (float(fields["xacc"]), float(fields["yacc"]), float(fields["zacc"]))
                if not _finite(*acc, t_s) or max(abs(a) for a in acc) > ACCEL_PLAUSIBLE_M_S2:
                    return self._reject("HIGHRES_IMU accelerometer non-finite or implausible")
                if self.accel and t_s <= self.accel[-1].t_s:
                    return self._reject("HIGHRES_IMU out of order")
                self.accel.append(AccelSample(t_s, acc))
                return True
            if name in ("ATTITUDE_TARGET", "EXTENDED_SYS_STATE"):
                if self._autopilot_sysid is not None and src_sysid != self._autopilot_sysid:
                    return self._reject(f"{name} not from the autopilot")
                if name == "EXTENDED_SYS_STATE":
                    self.landed_state = int(fields["landed_state"])
                    return True
                thr = float(fields["thrust"])
                if not (_finite(thr, t_s) and 0.0 <= thr <= 1.0):
                    return self._reject("ATTITUDE_TARGET thrust not in [0, 1]")
                if self.thrust_setpoints and t_s <= self.thrust_setpoints[-1].t_s:
                    return self._reject("ATTITUDE_TARGET out of order")
                self.thrust_setpoints.append(ThrustSample(t_s, thr))
                return True
            if name == "HEARTBEAT":
                custom = int(fields["custom_mode"])
                self.mode = VehicleMode(
                    t_s,
                    armed=bool(int(fields["base_mode"]) & 128),
                    main_mode=(custom >> 16) & 0xFF,
                    sub_mode=(custom >> 24) & 0xFF,
                )
                return True
        except (KeyError, TypeError, ValueError):
            return self._reject(f"{name} malformed")
        return False

    def _push_attitude(self, name: str, s: AttitudeSample) -> bool:
        """One attitude history for both attitude messages (PX4 sends the same estimate as
        ATTITUDE and ATTITUDE_QUATERNION): a sample older than the newest is not used, one of
        the same instant replaces it."""
        if self.attitude and s.t_s <= self.attitude[-1].t_s:
            if s.t_s < self.attitude[-1].t_s:
                return self._reject(f"{name} out of order")
            self.attitude.pop()  # the same instant from the other message: the newer one
        self.attitude.append(s)
        return True

    def _follow_target(self, f: Mapping[str, Any], t_s: float) -> bool:
        caps = int(f["est_capabilities"])
        if caps & 0b11 != 0b11:
            return self._reject("FOLLOW_TARGET without position and velocity")
        lat = int(f["lat"]) * 1e-7
        lon = int(f["lon"]) * 1e-7
        alt = float(f["alt"])
        vel = tuple([float(v) for v in f["vel"]])  # a list first: cheaper than a generator
        acc = tuple([float(v) for v in f["acc"]]) if caps & 0b100 else (0.0, 0.0, 0.0)
        q = [float(v) for v in f["attitude_q"]]
        rates = [float(v) for v in f["rates"]]
        if not _finite(lat, lon, alt, *vel, *acc):
            return self._reject("FOLLOW_TARGET non-finite")
        if caps & 0b1000 and _finite(*q, *rates) and abs(_norm(q) - 1.0) < 1e-3:
            yaw = euler_zyx_from_quat(q)[2]
            yaw_rate = rates[2]
        else:  # heading from the velocity when the AGV does not send its attitude
            yaw = math.atan2(vel[1], vel[0])
            yaw_rate = 0.0
        self.target = TargetSample(
            t_s, self.ned_from_geodetic(lat, lon, alt), vel, acc, yaw, yaw_rate  # type: ignore[arg-type]
        )
        return True

    def ned_from_geodetic(
        self, lat_deg: float, lon_deg: float, alt_m: float
    ) -> tuple[float, float, float]:
        """Local tangent-plane NED about the configured origin (adequate over a few km)."""
        lat0, lon0, alt0 = self._origin
        north = math.radians(lat_deg - lat0) * EARTH_RADIUS_M
        east = math.radians(lon_deg - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
        return (north, east, alt0 - alt_m)

    def _reject(self, why: str) -> bool:
        self.rejected[why] = self.rejected.get(why, 0) + 1
        return False

    # -- queries ----------------------------------------------------------------------------

    def attitude_at(self, t_s: float, max_extrapolation_s: float = 0.05) -> AttitudeSample | None:
        """Attitude interpolated (slerp) to ``t_s``; held from the newest sample up to
        ``max_extrapolation_s`` past it; ``None`` if no sample brackets ``t_s``."""
        if not self.attitude:
            return None
        newest = self.attitude[-1]
        if t_s >= newest.t_s:
            return newest if t_s - newest.t_s <= max_extrapolation_s else None
        prev = None
        for s in reversed(self.attitude):
            if s.t_s <= t_s:
                prev = s
                break
            nxt = s
        if prev is None:
            return None
        span = nxt.t_s - prev.t_s
        w = 0.0 if span <= 0 else (t_s - prev.t_s) / span
        q = _slerp(prev.q_wxyz, nxt.q_wxyz, w)
        rate = prev.yaw_rate_rad_s + w * (nxt.yaw_rate_rad_s - prev.yaw_rate_rad_s)
        return make(AttitudeSample, t_s=t_s, q_wxyz=q, yaw_rate_rad_s=rate)

    def autopilot_thrust_over(self, t0_s: float, t1_s: float,
                              max_age_s: float = 0.25) -> float | None:
        """The autopilot's own thrust setpoint over ``[t0_s, t1_s]``, time-weighted with each
        ATTITUDE_TARGET held until the next; ``None`` unless a sample at most ``max_age_s``
        old was in force at ``t0_s`` and the vehicle reports being in the air."""
        hist = self.thrust_setpoints
        if self.landed_state != 2 or not hist or t1_s <= t0_s:  # MAV_LANDED_STATE_IN_AIR
            return None
        first = None
        for i in range(len(hist) - 1, -1, -1):
            if hist[i].t_s <= t0_s + 1e-9:
                first = i
                break
        if first is None or t0_s - hist[first].t_s > max_age_s:
            return None
        total = 0.0
        for i in range(first, len(hist)):
            end = hist[i + 1].t_s if i + 1 < len(hist) else math.inf
            lo, hi = max(hist[i].t_s, t0_s), min(end, t1_s)
            if hi > lo:
                total += hist[i].thrust_norm * (hi - lo)
        return total / (t1_s - t0_s)

    def kinematics_at(self, t_s: float) -> KinematicsSample | None:
        """Position and velocity linearly interpolated to ``t_s``; the newest sample when
        ``t_s`` is at or after it; the oldest kept when ``t_s`` is before it; ``None`` if none."""
        hist = self.kinematics_history
        if not hist:
            return None
        if t_s >= hist[-1].t_s:
            return hist[-1]
        nxt = hist[-1]
        for s in reversed(hist):
            if s.t_s <= t_s:
                span = nxt.t_s - s.t_s
                w = 0.0 if span <= 0 else (t_s - s.t_s) / span
                # a + w (b - a) per element in plain floats (numpy's values, less overhead)
                pos = tuple(a + w * (b - a) for a, b in zip(s.pos_ned_m, nxt.pos_ned_m,
                                                            strict=True))
                vel = tuple(a + w * (b - a) for a, b in zip(s.vel_ned_m_s, nxt.vel_ned_m_s,
                                                            strict=True))
                return make(KinematicsSample, t_s=t_s, pos_ned_m=pos, vel_ned_m_s=vel)
            nxt = s
        return hist[0]

    def newest_autopilot_s(self) -> float:
        """The newest attitude or position stamp (``-inf`` if none)."""
        ts = [self.attitude[-1].t_s] if self.attitude else []
        if self.kinematics is not None:
            ts.append(self.kinematics.t_s)
        return max(ts, default=-math.inf)

    def telemetry_age_s(self, t_s: float) -> float:
        """Age of the older of the newest attitude and kinematics samples (``inf`` if none)."""
        if not self.attitude or self.kinematics is None:
            return math.inf
        return t_s - min(self.attitude[-1].t_s, self.kinematics.t_s)

    def target_age_s(self, t_s: float) -> float:
        return math.inf if self.target is None else t_s - self.target.t_s


def _finite(*xs: Any) -> bool:
    isfinite = math.isfinite
    for x in xs:  # noqa: SIM110 - every accepted message: a plain loop, no generator
        if not isfinite(float(x)):
            return False
    return True


def _norm(q: Sequence[float]) -> float:
    """Euclidean norm of a few floats (a unit-quaternion check: numpy's call overhead on a
    tuple cost more than the check)."""
    return math.sqrt(sum(x * x for x in q))


def _slerp(q0: tuple[float, float, float, float], q1: tuple[float, float, float, float],
           w: float) -> tuple[float, float, float, float]:
    """Spherical interpolation of unit quaternions, normalised (plain floats: numpy's
    per-call overhead on 4-vectors cost more than the arithmetic; the same values)."""
    dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    if dot < 0.0:
        q1 = (-q1[0], -q1[1], -q1[2], -q1[3])
        dot = -dot
    if dot > 0.9995:
        q = [a + w * (b - a) for a, b in zip(q0, q1, strict=True)]
    else:
        th = math.acos(dot)
        s0, s1, st = math.sin((1 - w) * th), math.sin(w * th), math.sin(th)
        q = [(s0 * a + s1 * b) / st for a, b in zip(q0, q1, strict=True)]
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
