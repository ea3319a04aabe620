"""Quadrotor model of the emulator: translational dynamics in NED, attitude as a rate-limited
first-order response to the setpoint. Pure numpy, fixed-step, deterministic.

Frames: world NED, body FRD; quaternions are w,x,y,z (body FRD relative to NED, as MAVLink's
ATTITUDE_QUATERNION). Euler angles are ZYX (yaw psi, pitch theta, roll phi).

Translational model (PX4 maps normalised thrust to acceleration with ``MPC_THR_HOVER``)::

    a_NED = R(q) [0, 0, -g T / T_hover] + [0, 0, g] - drag * v + d(t)

Attitude model: each of roll, pitch, yaw moves towards its setpoint as a first-order lag with
time constant ``attitude_tau_s``; roll/pitch speed is limited to ``max_tilt_rate_rad_s``, yaw
speed to ``max_yaw_rate_rad_s`` (after the yaw-rate feed-forward is added). The setpoint's tilt
is clipped to ``max_tilt_rad`` first (roll and pitch scaled together).

Ground contact: the ground is the plane ``z = ground_z_m`` (NED, down positive); the vehicle
cannot go below it and, while pressed onto it, its velocity is zero.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from sim_bridge.physics.rigid_body import CascadeState

Vec = NDArray[np.float64]

G_M_S2 = 9.81


# --------------------------------------------------------------------------------------------
# Rotations
def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vec:
    """ZYX Euler -> quaternion w,x,y,z (body FRD relative to NED)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def euler_from_quat(q_wxyz: Vec) -> tuple[float, float, float]:
    """Quaternion w,x,y,z -> ZYX Euler (roll, pitch, yaw) in rad. Normalises ``q`` first."""
    q = np.asarray(q_wxyz, dtype=float)
    n = float(np.linalg.norm(q))
    if not n > 0 or not math.isfinite(n):
        raise ValueError("quaternion must have a finite, non-zero norm")
    w, x, y, z = q / n
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def rot_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vec:
    """Rotation matrix body FRD -> NED, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (3x3)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def wrap_pi(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def clip_tilt(roll_rad: float, pitch_rad: float, max_tilt_rad: float) -> tuple[float, float]:
    """Scale roll and pitch together so that the tilt ``acos(cos(roll) cos(pitch))`` is at most
    ``max_tilt_rad``."""
    tilt = math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))
    if tilt <= max_tilt_rad:
        return roll_rad, pitch_rad
    lo, hi = 0.0, 1.0  # bisection on the common scale factor (tilt is monotonic in it)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        t = math.acos(max(-1.0, min(1.0, math.cos(mid * roll_rad) * math.cos(mid * pitch_rad))))
        if t > max_tilt_rad:
            hi = mid
        else:
            lo = mid
    return lo * roll_rad, lo * pitch_rad


# --------------------------------------------------------------------------------------------
# Parameters, commands, state
@dataclass(frozen=True)
class VehicleParams:
    hover_thrust: float = 0.5
    attitude_tau_s: float = 0.08
    max_tilt_rate_rad_s: float = 3.0
    max_yaw_rate_rad_s: float = 1.5
    drag_per_s: float = 0.05
    max_tilt_rad: float = 0.6
    ground_z_m: float = 0.0
    g_m_s2: float = G_M_S2
    # battery sag: the hover thrust at t is hover_thrust / (1 - min(max_loss, loss_per_s t))
    battery_loss_per_s: float = 0.0
    battery_max_loss: float = 0.0

    def __post_init__(self) -> None:
        if not (self.battery_loss_per_s >= 0 and 0 <= self.battery_max_loss < 0.9):
            raise ValueError("invalid battery parameters")
        if not 0 < self.hover_thrust < 1:
            raise ValueError("hover_thrust must be in (0, 1)")
        if not (self.attitude_tau_s > 0 and self.max_tilt_rate_rad_s > 0
                and self.max_yaw_rate_rad_s > 0 and self.drag_per_s >= 0
                and 0 < self.max_tilt_rad < math.pi / 2):
            raise ValueError("invalid vehicle parameters")


@dataclass(frozen=True)
class DisturbanceParams:
    """``d(t) = wind + gust_amplitude sin(2 pi t / gust_period) e_gust + w_k`` (m/s^2, NED).

    ``e_gust`` is the unit direction of the horizontal wind (north when there is none).
    ``w_k`` is uniform in the ball of radius ``random_bound_m_s2``, drawn from ``seed`` and the
    index ``k = floor(t / random_hold_s)`` alone, so it does not depend on the step size or
    on how often it is evaluated.

    Turbulence (added to ``d``): ``x_{k+1} = a x_k + sqrt(1 - a^2) sigma n_k`` with ``a =
    exp(-h / turbulence_tau_s)``, ``h = random_hold_s``, ``n_k`` standard normal from ``seed``
    and ``k`` (so it is the same at any step size), sigma = ``turbulence_std_m_s2`` north and
    east, half of it down; ``x_0`` is drawn from the stationary distribution.
    """

    wind_accel_ned_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_amplitude_m_s2: float = 0.0
    gust_period_s: float = 10.0
    random_bound_m_s2: float = 0.0
    random_hold_s: float = 0.05
    seed: int = 0
    turbulence_std_m_s2: float = 0.0
    turbulence_tau_s: float = 2.0


class Disturbance:
    """Deterministic disturbance acceleration ``d(t)`` (see :class:`DisturbanceParams`)."""

    def __init__(self, params: DisturbanceParams) -> None:
        self.params = params
        wind = np.asarray(params.wind_accel_ned_m_s2, dtype=float)
        h = float(np.hypot(wind[0], wind[1]))
        self._gust_dir = np.array([wind[0] / h, wind[1] / h, 0.0]) if h > 0 else np.array(
            [1.0, 0.0, 0.0])
        self._wind = wind
        self._cache_k = -1
        self._cache_w = np.zeros(3)
        self._turb_k = -1
        self._turb = np.zeros(3)
        self._held_k: int | None = None
        self._held = np.zeros(3)
        self._turb_sigma = params.turbulence_std_m_s2 * np.array([1.0, 1.0, 0.5])
        self._turb_a = math.exp(-params.random_hold_s / params.turbulence_tau_s)

    def _noise(self, k: int) -> Vec:
        rng = np.random.default_rng([self.params.seed & 0xFFFFFFFF, 7, k])
        out: Vec = rng.normal(size=3)
        return out

    def _turbulence(self, k: int) -> Vec:
        if k < self._turb_k or self._turb_k < 0:  # (re)start from the stationary state
            self._turb_k = 0
            self._turb = self._noise(0) * self._turb_sigma
        a = self._turb_a
        b = math.sqrt(1.0 - a * a)
        while self._turb_k < k:
            self._turb_k += 1
            self._turb = a * self._turb + b * self._turb_sigma * self._noise(self._turb_k)
        return self._turb

    def _random(self, k: int) -> Vec:
        if k != self._cache_k:
            rng = np.random.default_rng([self.params.seed & 0xFFFFFFFF, k])
            v = rng.normal(size=3)
            n = float(np.linalg.norm(v))
            r = rng.uniform() ** (1 / 3)
            self._cache_w = (v / n) * r * self.params.random_bound_m_s2 if n > 0 else np.zeros(3)
            self._cache_k = k
        return self._cache_w

    def accel_ned_m_s2(self, t_s: float) -> Vec:
        """``d(t)`` (m/s^2, NED). Read-only: without a gust the value is constant over each
        ``random_hold_s`` and the same array is returned for the whole interval."""
        p = self.params
        k = math.floor(t_s / p.random_hold_s)
        if p.gust_amplitude_m_s2 <= 0 and k == self._held_k:
            return self._held
        d = self._wind.copy()
        if p.gust_amplitude_m_s2 > 0:
            d += p.gust_amplitude_m_s2 * math.sin(2 * math.pi * t_s / p.gust_period_s) \
                * self._gust_dir
        if p.random_bound_m_s2 > 0:
            d += self._random(k)
        if p.turbulence_std_m_s2 > 0:
            d += self._turbulence(max(0, k))
        d.flags.writeable = False
        self._held_k, self._held = k, d
        return d


@dataclass(frozen=True)
class AttitudeCommand:
    """What the attitude/thrust loop tracks.

    ``roll/pitch/yaw_rad``: setpoint (ZYX, rad). ``thrust_norm``: 0..1 along body -z.
    ``yaw_rate_ff_rad_s``: Earth-frame yaw-rate feed-forward added to the yaw loop.
    ``motors_on``: False when disarmed or terminated (no thrust, attitude uncontrolled).
    ``body_rates_frd_rad_s``: an offboard body-rate setpoint; the px4 model feeds it to its
    rate controller (as PX4 does), the first-order model tracks the attitude integrated from it.
    """

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_norm: float
    yaw_rate_ff_rad_s: float = 0.0
    motors_on: bool = True
    body_rates_frd_rad_s: tuple[float, float, float] | None = None

    @staticmethod
    def from_quat(q_wxyz: Vec, thrust_norm: float, yaw_rate_ff_rad_s: float = 0.0
                  ) -> AttitudeCommand:
        r, p, y = euler_from_quat(q_wxyz)
        return AttitudeCommand(r, p, y, thrust_norm, yaw_rate_ff_rad_s)


MOTORS_OFF = AttitudeCommand(0.0, 0.0, 0.0, 0.0, 0.0, motors_on=False)


@dataclass(frozen=True)
class VehicleState:
    """Vehicle state at ``t_s`` (s since boot)."""

    t_s: float
    pos_ned_m: Vec
    vel_ned_m_s: Vec
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    euler_rates_rad_s: Vec = field(default_factory=lambda: np.zeros(3))
    acc_ned_m_s2: Vec = field(default_factory=lambda: np.zeros(3))
    thrust_norm: float = 0.0
    on_ground: bool = False
    disturbance_ned_m_s2: Vec = field(default_factory=lambda: np.zeros(3))
    # PX4 model only: the cascade's memory (``sim_bridge.physics.rigid_body``)
    cascade: CascadeState | None = None
    # the collective thrust that hovers the vehicle now (battery, payload), NaN if unknown
    hover_thrust_true: float = math.nan

    # Derived once per state (a step's state is read by the camera, the telemetry and the
    # ground truth: ~8 conversions a step); read-only, as the state is.
    @functools.cached_property
    def q_wxyz(self) -> Vec:
        return _read_only(quat_from_euler(self.roll_rad, self.pitch_rad, self.yaw_rad))

    @functools.cached_property
    def rot_body_to_ned(self) -> Vec:
        return _read_only(rot_from_euler(self.roll_rad, self.pitch_rad, self.yaw_rad))

    @functools.cached_property
    def rates_frd_rad_s(self) -> Vec:
        """Body rates (p, q, r) from the Euler rates (ZYX kinematics)."""
        dr, dp, dy = (float(v) for v in self.euler_rates_rad_s)
        sr, cr = math.sin(self.roll_rad), math.cos(self.roll_rad)
        sp, cp = math.sin(self.pitch_rad), math.cos(self.pitch_rad)
        return _read_only(np.array([dr - sp * dy, cr * dp + sr * cp * dy,
                                    -sr * dp + cr * cp * dy]))


def _read_only(a: Vec) -> Vec:
    a.flags.writeable = False
    return a


def initial_state(pos_ned_m: tuple[float, float, float] | Vec, roll_rad: float = 0.0,
                  pitch_rad: float = 0.0, yaw_rad: float = 0.0, t_s: float = 0.0,
                  on_ground: bool = False) -> VehicleState:
    return VehicleState(t_s=t_s, pos_ned_m=np.asarray(pos_ned_m, dtype=float).copy(),
                        vel_ned_m_s=np.zeros(3), roll_rad=roll_rad, pitch_rad=pitch_rad,
                        yaw_rad=yaw_rad, on_ground=on_ground)


# --------------------------------------------------------------------------------------------
class _Substate(NamedTuple):
    """The integrator's state between sub-steps (plain floats)."""

    t_s: float
    px: float
    py: float
    pz: float
    vx: float
    vy: float
    vz: float
    roll: float
    pitch: float
    yaw: float
    on_ground: bool


class _Outputs(NamedTuple):
    """What a sub-step derived besides its state (kept for the last one)."""

    euler_rates: tuple[float, float, float]
    acc: tuple[float, float, float]
    thrust: float
    dist: Vec
    hover: float


class _Held(NamedTuple):
    """What the command held over a step fixes for each of its sub-steps."""

    cmd: AttitudeCommand
    alpha: float  # the attitude lag's factor per sub-step, 1 - exp(-dt / tau)
    thrust: float  # clipped to 0..1, 0 with the motors off
    roll_sp: float  # the tilt setpoint clipped to max_tilt_rad
    pitch_sp: float


class VehicleModel:
    """Fixed-step integrator. ``step(state, cmd, duration_s)`` advances by whole ``dt_s``
    sub-steps (``round(duration_s / dt_s)`` of them, at least one) with the command held."""

    def __init__(self, params: VehicleParams, disturbance: Disturbance | None = None,
                 dt_s: float = 0.0025) -> None:
        if not dt_s > 0:
            raise ValueError("dt_s must be > 0")
        self.params = params
        self.disturbance = disturbance or Disturbance(DisturbanceParams())
        self.dt_s = dt_s
        self._dist_last: Vec | None = None
        self._dist_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def _dist_floats(self, dist: Vec) -> tuple[float, float, float]:
        """``dist`` as floats; the disturbance returns the same array while it is constant."""
        if dist is not self._dist_last:
            self._dist_last, self._dist_xyz = dist, tuple(dist.tolist())
        return self._dist_xyz

    def true_hover_thrust(self, t_s: float) -> float:
        """The thrust that hovers the vehicle at ``t_s`` (``hover_thrust`` over the battery's
        thrust factor)."""
        p = self.params
        return p.hover_thrust / (1.0 - min(p.battery_max_loss,
                                           p.battery_loss_per_s * max(0.0, t_s)))

    def specific_thrust_ned(self, roll: float, pitch: float, yaw: float,
                            thrust_norm: float, t_s: float = 0.0) -> Vec:
        """``R(q) [0, 0, -g T / T_hover(t)]`` (m/s^2, NED)."""
        p = self.params
        out: Vec = rot_from_euler(roll, pitch, yaw) @ np.array(
            [0.0, 0.0, -p.g_m_s2 * thrust_norm / self.true_hover_thrust(t_s)])
        return out

    def step(self, s: VehicleState, cmd: AttitudeCommand, duration_s: float) -> VehicleState:
        """``round(duration_s / dt_s)`` sub-steps (at least one) with ``cmd`` held. The
        sub-steps run on plain floats in one loop (:meth:`_substeps`) and only the last one
        becomes a :class:`VehicleState` (a 20-fold saving of small numpy arrays per lockstep
        step); every operation is the one the array form did, in the same order, so the result
        is the same to the bit. What the held command fixes (the clipped tilt setpoint, the
        thrust, the lag's factor) is worked out once per step: the same numbers each sub-step
        computed before."""
        n = max(1, round(duration_s / self.dt_s))
        pos, vel = s.pos_ned_m, s.vel_ned_m_s
        x = _Substate(s.t_s, float(pos[0]), float(pos[1]), float(pos[2]), float(vel[0]),
                      float(vel[1]), float(vel[2]), s.roll_rad, s.pitch_rad, s.yaw_rad,
                      s.on_ground)
        x, out = self._substeps(x, self._held(cmd), n)
        return VehicleState(t_s=x.t_s, pos_ned_m=np.array([x.px, x.py, x.pz]),
                            vel_ned_m_s=np.array([x.vx, x.vy, x.vz]), roll_rad=x.roll,
                            pitch_rad=x.pitch, yaw_rad=x.yaw,
                            euler_rates_rad_s=np.array(out.euler_rates),
                            acc_ned_m_s2=np.array(out.acc), thrust_norm=out.thrust,
                            on_ground=x.on_ground, disturbance_ned_m_s2=out.dist,
                            hover_thrust_true=out.hover)

    def _held(self, cmd: AttitudeCommand) -> _Held:
        """What ``cmd`` fixes for every sub-step of a step."""
        p, dt = self.params, self.dt_s
        r_sp, p_sp = (clip_tilt(cmd.roll_rad, cmd.pitch_rad, p.max_tilt_rad) if cmd.motors_on
                      else (0.0, 0.0))
        return _Held(cmd, 1.0 - math.exp(-dt / p.attitude_tau_s),
                     min(1.0, max(0.0, cmd.thrust_norm)) if cmd.motors_on else 0.0, r_sp, p_sp)

    def _substeps(self, x: _Substate, h: _Held, n: int) -> tuple[_Substate, _Outputs]:
        """``n`` sub-steps of ``dt_s`` from ``x``: first-order attitude tracking (rate-limited),
        then semi-implicit Euler on the translation with the ground's contact. One loop on
        local floats: the per-sub-step calls and tuples cost ~60 % of the physics' CPU (the
        same operations in the same order as before, tests/sim/test_physics_substeps.py)."""
        p, dt, cmd, alpha, thrust = self.params, self.dt_s, h.cmd, h.alpha, h.thrust
        on = cmd.motors_on
        roll_sp, pitch_sp, yaw_sp, ff_dt = h.roll_sp, h.pitch_sp, cmd.yaw_rad, \
            cmd.yaw_rate_ff_rad_s * dt
        lim, ylim = p.max_tilt_rate_rad_s * dt, p.max_yaw_rate_rad_s * dt
        g, drag, ground_z = p.g_m_s2, p.drag_per_s, p.ground_z_m
        hover_of, dist_of, floats_of = self.true_hover_thrust, \
            self.disturbance.accel_ned_m_s2, self._dist_floats
        pi, two_pi, cos, sin = math.pi, 2 * math.pi, math.cos, math.sin
        t, px, py, pz, vx, vy, vz, roll, pitch, yaw, on_ground = x
        d_roll = d_pitch = d_yaw = ax = ay = az = hover = 0.0
        dist = None
        for _ in range(n):
            if on:  # wrap_pi and _clamp written out
                d_roll = alpha * ((roll_sp - roll + pi) % two_pi - pi)
                d_roll = -lim if d_roll < -lim else (lim if d_roll > lim else d_roll)
                d_pitch = alpha * ((pitch_sp - pitch + pi) % two_pi - pi)
                d_pitch = -lim if d_pitch < -lim else (lim if d_pitch > lim else d_pitch)
                d_yaw = alpha * ((yaw_sp - yaw + pi) % two_pi - pi) + ff_dt
                d_yaw = -ylim if d_yaw < -ylim else (ylim if d_yaw > ylim else d_yaw)
            else:
                d_roll = d_pitch = d_yaw = 0.0
            hover = hover_of(t)
            if on_ground and (thrust <= hover or not on):
                # resting on the ground: no tipping over below lift-off thrust
                d_roll, d_pitch = -roll * alpha, -pitch * alpha
            roll, pitch, yaw = roll + d_roll, pitch + d_pitch, (yaw + d_yaw + pi) % two_pi - pi
            dist = dist_of(t)
            dx, dy, dz = floats_of(dist)
            t = t + dt
            # specific thrust R(roll, pitch, yaw) [0, 0, c]: R's third column times c
            c = -g * thrust / hover
            cr, sr = cos(roll), sin(roll)
            cp, sp = cos(pitch), sin(pitch)
            cy, sy = cos(yaw), sin(yaw)
            ax = (((cy * sp * cr + sy * sr) * c + 0.0) - drag * vx) + dx
            ay = (((sy * sp * cr - cy * sr) * c + 0.0) - drag * vy) + dy
            az = (((cp * cr) * c + g) - drag * vz) + dz
            x_px, x_py = px, py
            vx, vy, vz = vx + ax * dt, vy + ay * dt, vz + az * dt
            px, py, pz = px + vx * dt, py + vy * dt, pz + vz * dt  # semi-implicit Euler
            was_on_ground, on_ground = on_ground, False
            if pz >= ground_z:
                if az >= 0 or vz >= 0:
                    # pressed onto (or sinking into) the ground: it stops there, no sliding
                    if was_on_ground:
                        px, py = x_px, x_py
                    pz = ground_z
                    vx = vy = vz = ax = ay = az = 0.0
                    on_ground = True
                else:
                    pz = ground_z
        assert dist is not None
        return (_Substate(t, px, py, pz, vx, vy, vz, roll, pitch, yaw, on_ground),
                _Outputs((d_roll / dt, d_pitch / dt, d_yaw / dt), (ax, ay, az), thrust, dist,
                         hover))
