"""The emulator's vehicle on rotorpy (MIT; github.com/spencerfolk/rotorpy): PX4's attitude and rate
cascade (ours, :mod:`sim_bridge.physics.px4_control`) commands the rotor speeds of rotorpy's
``Multirotor`` (its equations, :mod:`sim_bridge.physics.rotorpy_dynamics`: rigid body, first-order
rotor-speed dynamics, parasitic drag, rotor drag, induced inflow, translational lift, blade
flapping), the airframe is rotorpy's AscTec Hummingbird preset with its maximum rotor speed scaled
so that it hovers at our vehicle's true hover thrust, and the wind is rotorpy's Dryden turbulence
(:mod:`sim_bridge.physics.rotorpy_wind`). The same interface as
:class:`sim_bridge.physics.rigid_body.Px4VehicleModel`; docs/reference/rotorpy.md.

Per sub-step ``dt_s`` (the emulator's ``physics_dt_s``)::

    q, w  <- rotorpy's state (ENU / FLU) as NED / FRD
    u_i   <- PX4: attitude P -> rate PID -> allocation -> THR_MDL_FAC inversion (as rigid_body)
    w_cmd_i = w_max sqrt(b(t) c_k(u_i))     the ESC: relative thrust c_k(u) (k = the TRUE curve,
                                            ``motor_curve_factor``), thrust ~ w^2, battery b(t)
    rotorpy: s' = Multirotor._s_dot_fn(s, w_cmd)   integrated by classic RK4 over dt_s

The derivative is rotorpy's, transcribed to floats (:mod:`sim_bridge.physics.rotorpy_dynamics`,
checked against rotorpy's own function), and integrated by RK4 rather than rotorpy's
``Multirotor.step`` (scipy ``solve_ivp``, RK45): 9 ms of CPU per 2.5 ms sub-step with solve_ivp
here, 0.9 ms with RK4 on rotorpy's numpy derivative, ~0.1 ms on the transcription; the fixed
step is one the lockstep emulator reproduces. The tests check the integrations agree.

Frames: rotorpy's world is ENU with z up from the ground (``ground_z_m`` NED is rotorpy's z = 0,
its ground plane), its body FLU; the emulator's world is NED, its body FRD. Rotor order and spin
directions are PX4's quad X (as rotorpy's own PX4 SIH preset), so PX4's allocation applies as is.

Pure: numpy, math and rotorpy's vehicle module (no I/O); the controller's and rotorpy's state
travel in ``VehicleState.cascade`` (:class:`RotorpyCascade`).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from rotorpy.vehicles.hummingbird_params import quad_params as hummingbird_params

from sim_bridge.physics.px4_control import (
    QUAD_X_POS,
    QUAD_X_YAW,
    V3,
    Px4Gains,
    Quat,
    RateState,
    allocate,
    attitude_control,
    qmul,
    qnormalize,
    rate_control,
    saturation_flags,
    thrust_curve,
    thrust_curve_inverse,
)
from sim_bridge.physics.rigid_body import CascadeState, battery_factor
from sim_bridge.physics.rotorpy_dynamics import RotorpyDerivative
from sim_bridge.physics.rotorpy_wind import DrydenParams, DrydenWind, WindState
from sim_bridge.physics.vehicle import (
    G_M_S2,
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleState,
    euler_from_quat,
    quat_from_euler,
)

_S = math.sqrt(0.5)
# NED <-> ENU is the half turn about (1, 1, 0)/sqrt 2, FRD <-> FLU the half turn about x:
# q_ned_frd = Q_ENU_NED (x) q_enu_flu (x) Q_FLU_FRD (each its own inverse up to sign)
Q_ENU_NED: Quat = (0.0, _S, _S, 0.0)
Q_FLU_FRD: Quat = (0.0, 1.0, 0.0, 0.0)
# rotorpy's state vector: x (0:3), v (3:6), q x,y,z,w (6:10), w (10:13), wind (13:16), rotors
_X, _V, _Q, _W, _WIND, _ROT = 0, 3, 6, 10, 13, 16
_ON_GROUND_Z_M = 0.001  # rotorpy's Multirotor._on_ground


def ned_from_enu(q_xyzw: Any) -> Quat:
    """rotorpy's attitude (x, y, z, w of body FLU in ENU) as w, x, y, z of body FRD in NED."""
    q: Quat = (float(q_xyzw[3]), float(q_xyzw[0]), float(q_xyzw[1]), float(q_xyzw[2]))
    return qnormalize(qmul(qmul(Q_ENU_NED, q), Q_FLU_FRD))


def enu_from_ned(q_wxyz: Quat) -> tuple[float, float, float, float]:
    """Inverse of :func:`ned_from_enu` (x, y, z, w, rotorpy's order)."""
    w, x, y, z = qnormalize(qmul(qmul(Q_ENU_NED, q_wxyz), Q_FLU_FRD))
    return x, y, z, w


@dataclass(frozen=True)
class RotorpyAirframe:
    """The vehicle we fly: rotorpy's Hummingbird preset, rotors in PX4's quad-X order and spin,
    maximum rotor speed scaled to the true hover thrust; the vehicle's imperfections as in
    :class:`sim_bridge.physics.rigid_body.AirframeParams` (its linear drag aside: rotorpy's
    aerodynamics replace it)."""

    true_hover_thrust: float = 0.5  # command that hovers the nominal vehicle, full battery
    motor_curve_factor: float = 0.0  # the motors' TRUE thrust curve k (PX4 assumes THR_MDL_FAC)
    mass_error: float = 0.0  # payload: mass and inertia x (1 + mass_error)
    battery_loss_per_s: float = 0.0
    battery_max_loss: float = 0.0
    ground_z_m: float = 0.0
    aero: bool = True  # rotorpy's aerodynamic wrenches (drag, rotor drag, inflow, lift, flapping)

    def __post_init__(self) -> None:
        if not 0 < self.true_hover_thrust < 1:
            raise ValueError("true_hover_thrust: must be in (0, 1)")
        if not 0 <= self.motor_curve_factor <= 1:
            raise ValueError("motor_curve_factor: must be in [0, 1]")
        if not (-0.5 < self.mass_error < 1.0 and self.battery_loss_per_s >= 0
                and 0 <= self.battery_max_loss < 0.9):
            raise ValueError("invalid vehicle imperfections")


def quad_params(airframe: RotorpyAirframe, thr_mdl_fac: float) -> dict[str, Any]:
    """rotorpy's ``quad_params`` for ``airframe``: the Hummingbird's (mass 0.5 kg, inertia,
    arm 0.17 m, k_eta, k_m, tau_m 5 ms, drag and rotor aerodynamics), with

    * the rotors at the Hummingbird's radius, in PX4's quad-X order (front-right, rear-left,
      front-left, rear-right) and spin, so that PX4's allocation drives them;
    * ``rotor_speed_max`` such that the true hover command (through PX4's THR_MDL_FAC inversion
      and the true motor curve) hovers the nominal vehicle: ``4 k_eta w_max^2 c_k(u_hover) = m
      g`` (the Hummingbird itself hovers at ~10 % of its 1500 rad/s^2 thrust; ours does not);
    * mass and inertia x (1 + mass_error) (the motors stay the nominal vehicle's).
    """
    p: dict[str, Any] = copy.deepcopy(hummingbird_params)
    m_nom = float(p["mass"])
    hover_rel = thrust_curve(thrust_curve_inverse(airframe.true_hover_thrust, thr_mdl_fac),
                             airframe.motor_curve_factor)
    f_max_n = m_nom * G_M_S2 / (4.0 * hover_rel)
    p["rotor_speed_max"] = math.sqrt(f_max_n / float(p["k_eta"]))
    p["rotor_speed_min"] = 0.0
    arm_xy_m = float(np.linalg.norm(p["rotor_pos"]["r1"][:2])) * _S
    # FRD (x, y) -> FLU (x, -y); PX4's yaw sign is about FRD z (down), rotorpy's about FLU z (up)
    p["rotor_pos"] = {f"r{i + 1}": np.array([arm_xy_m * x, -arm_xy_m * y, 0.0])
                      for i, (x, y) in enumerate(QUAD_X_POS)}
    p["rotor_directions"] = np.array([-v for v in QUAD_X_YAW])
    scale = 1.0 + airframe.mass_error
    p["mass"] = m_nom * scale
    for k in ("Ixx", "Iyy", "Izz", "Ixy", "Iyz", "Ixz"):
        p[k] = float(p[k]) * scale
    return p


@dataclass(frozen=True)
class RotorpyCascade(CascadeState):
    """:class:`CascadeState` (attitude, rates, the rate controller, each motor's relative thrust)
    plus rotorpy's whole state vector and the wind's."""

    rotorpy_state: tuple[float, ...]
    wind: WindState


class RotorpyVehicleModel:
    """PX4's cascade driving rotorpy's Multirotor; ``step(state, cmd, duration_s)`` advances by
    whole ``dt_s`` sub-steps with the command held (like ``Px4VehicleModel``)."""

    def __init__(self, gains: Px4Gains, airframe: RotorpyAirframe,
                 disturbance: DisturbanceParams | None = None, dt_s: float = 0.0025,
                 wind_altitude_m: float = 2.0) -> None:
        if not dt_s > 0:
            raise ValueError("dt_s must be > 0")
        self.gains, self.params, self.dt_s = gains, airframe, dt_s
        self.quad = quad_params(airframe, gains.thr_mdl_fac)
        self.derivative = RotorpyDerivative(self.quad, aero=airframe.aero, enable_ground=True)
        self.mass_kg = float(self.quad["mass"])
        self.k_eta = float(self.quad["k_eta"])
        self.w_max_rad_s = float(self.quad["rotor_speed_max"])
        self.w_hover_rad_s = math.sqrt(self.mass_kg * G_M_S2 / (4.0 * self.k_eta))
        self.drag_per_s = self.linear_drag_per_s()
        d = disturbance or DisturbanceParams()
        # the acceleration table (wind, gust, bounded random) as air speed through rotorpy's
        # linearised drag; the turbulence as Dryden wind of the same std of acceleration
        self._steady = Disturbance(DisturbanceParams(
            wind_accel_ned_m_s2=d.wind_accel_ned_m_s2, gust_amplitude_m_s2=d.gust_amplitude_m_s2,
            gust_period_s=d.gust_period_s, random_bound_m_s2=d.random_bound_m_s2,
            random_hold_s=d.random_hold_s, seed=d.seed))
        cx, cz = self.drag_per_s
        self._wind_gain_ned = (1.0 / cx, 1.0 / cx, 1.0 / cz)
        sig = d.turbulence_std_m_s2
        self.dryden = DrydenWind(DrydenParams(std_m_s=(sig / cx, sig / cx, 0.5 * sig / cz),
                                              altitude_m=wind_altitude_m, dt_s=d.random_hold_s,
                                              seed=d.seed))

    # ---------------------------------------------------------------- derived figures
    def linear_drag_per_s(self) -> tuple[float, float]:
        """rotorpy's drag at hover, linearised at zero air speed (horizontal, vertical; 1/s):
        the rotor drag ``4 k_d w_hover / m`` and the induced inflow ``4 k_z w_hover / m`` (the
        parasitic drag is quadratic: nothing at zero air speed)."""
        q, n = self.quad, 4.0 * self.w_hover_rad_s / self.mass_kg
        kd, kz = float(q.get("k_d", 0.0)), float(q.get("k_z", 0.0))
        if not (kd > 0 and kz > 0) or not self.params.aero:
            raise ValueError("rotorpy airframe: the wind needs rotor drag (k_d, k_z > 0, aero)")
        return n * kd, n * kz

    def true_hover_thrust(self, t_s: float) -> float:
        """The collective thrust command that hovers the vehicle at ``t_s`` (battery, payload,
        both thrust curves): what PX4's hover-thrust estimator converges to."""
        a = self.params
        f_max = self.k_eta * self.w_max_rad_s**2 * battery_factor(
            t_s, a.battery_loss_per_s, a.battery_max_loss)
        rel = self.mass_kg * G_M_S2 / (4.0 * f_max)
        if rel >= 1.0:
            return 1.0
        k = a.motor_curve_factor
        u = rel if k <= 1e-7 else (-(1 - k) + math.sqrt((1 - k) ** 2 + 4 * k * rel)) / (2 * k)
        return thrust_curve(u, self.gains.thr_mdl_fac)

    def wind_enu_m_s(self, wind: WindState, t_s: float) -> np.ndarray:
        """Air velocity at ``t_s`` (ENU): the steady part plus the Dryden sample."""
        d = self._steady.accel_ned_m_s2(t_s)
        g = self._wind_gain_ned
        n, e, dn = float(d[0]) * g[0], float(d[1]) * g[1], float(d[2]) * g[2]
        return np.array([e + wind.wind_m_s[0], n + wind.wind_m_s[1], -dn + wind.wind_m_s[2]])

    def initial_cascade(self, s: VehicleState) -> RotorpyCascade:
        """For a state without one: its pose and rates, the rotors at the hover speed when
        airborne (an equilibrium), stopped on the ground."""
        q = tuple(float(v) for v in quat_from_euler(s.roll_rad, s.pitch_rad, s.yaw_rad))
        w = tuple(float(v) for v in s.rates_frd_rad_s)
        p, v = s.pos_ned_m, s.vel_ned_m_s
        rot = 0.0 if s.on_ground else self.w_hover_rad_s
        x = (float(p[1]), float(p[0]), self.params.ground_z_m - float(p[2]),
             float(v[1]), float(v[0]), -float(v[2]),
             *enu_from_ned(q), w[0], -w[1], -w[2], 0.0, 0.0, 0.0, rot, rot, rot, rot)  # type: ignore[arg-type]
        rel = (rot / self.w_max_rad_s) ** 2
        return RotorpyCascade(q, w, RateState(prev_rates_rad_s=w), (rel,) * 4,  # type: ignore[arg-type]
                              x, self.dryden.at(self.dryden.initial(), s.t_s))

    # ---------------------------------------------------------------- stepping
    def _rotor_commands(self, x: np.ndarray, cmd: AttitudeCommand, qd: Quat, rs: RateState,
                        t_s: float) -> tuple[np.ndarray, RateState, Quat, V3]:
        """PX4's cascade on the current state: the rotor-speed commands."""
        g, a = self.gains, self.params
        q = ned_from_enu(x[_Q:_Q + 4])
        w: V3 = (float(x[_W]), -float(x[_W + 1]), -float(x[_W + 2]))
        if not cmd.motors_on:
            return np.zeros(4), rs, q, w
        on_ground = float(x[_X + 2]) <= _ON_GROUND_Z_M
        rates_sp = cmd.body_rates_frd_rad_s
        w_sp = rates_sp if rates_sp is not None else attitude_control(
            q, qd, cmd.yaw_rate_ff_rad_s, g)
        torque, rs = rate_control(w, w_sp, rs, self.dt_s, on_ground, g)
        u, unalloc = allocate(torque, min(1.0, max(0.0, cmd.thrust_norm)))
        sat_pos, sat_neg = saturation_flags(unalloc)
        if sat_pos != rs.sat_pos or sat_neg != rs.sat_neg:
            rs = RateState(rs.integral, rs.ang_acc_rad_s2, rs.prev_rates_rad_s, sat_pos, sat_neg)
        w_top = self.w_max_rad_s * math.sqrt(
            battery_factor(t_s, a.battery_loss_per_s, a.battery_max_loss))
        out = np.array([
            w_top * math.sqrt(max(0.0, thrust_curve(thrust_curve_inverse(ui, g.thr_mdl_fac),
                                                    a.motor_curve_factor)))
            for ui in u])
        return out, rs, q, w

    def _rk4(self, x: np.ndarray, w_cmd: np.ndarray) -> np.ndarray:
        """One classic RK4 step of rotorpy's derivative with the rotor commands held; then
        rotorpy's own post-step: unit quaternion, ground contact."""
        f, h = self.derivative, self.dt_s
        k1 = f(x, w_cmd)
        k2 = f(x + 0.5 * h * k1, w_cmd)
        k3 = f(x + 0.5 * h * k2, w_cmd)
        k4 = f(x + h * k3, w_cmd)
        y: np.ndarray = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        y[_Q:_Q + 4] /= np.linalg.norm(y[_Q:_Q + 4])
        if f.on_ground(y):
            y = f.ground_contact(y)
        return y

    def step(self, s: VehicleState, cmd: AttitudeCommand, duration_s: float) -> VehicleState:
        n = max(1, round(duration_s / self.dt_s))
        cs = s.cascade if isinstance(s.cascade, RotorpyCascade) else self.initial_cascade(s)
        x = np.array(cs.rotorpy_state, dtype=float)
        rs, wind, t = cs.rate, cs.wind, s.t_s
        qd: Quat = tuple(float(v) for v in quat_from_euler(
            cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad))  # type: ignore[assignment]
        v_prev = x[_V:_V + 3].copy()
        w_max = float(self.quad["rotor_speed_max"])
        for _ in range(n):
            wind = self.dryden.at(wind, t)
            x[_WIND:_WIND + 3] = self.wind_enu_m_s(wind, t)
            w_cmd, rs, _, _ = self._rotor_commands(x, cmd, qd, rs, t)
            v_prev = x[_V:_V + 3].copy()
            x = self._rk4(x, np.clip(w_cmd, 0.0, w_max))
            t += self.dt_s
        return self._vehicle_state(x, v_prev, rs, wind, t, cmd)

    def _vehicle_state(self, x: np.ndarray, v_prev: np.ndarray, rs: RateState, wind: WindState,
                       t: float, cmd: AttitudeCommand) -> VehicleState:
        q = ned_from_enu(x[_Q:_Q + 4])
        w: V3 = (float(x[_W]), -float(x[_W + 1]), -float(x[_W + 2]))
        roll, pitch, yaw = euler_from_quat(np.array(q))
        on_ground = float(x[_X + 2]) <= _ON_GROUND_Z_M
        acc_enu = np.zeros(3) if on_ground else (x[_V:_V + 3] - v_prev) / self.dt_s
        rotors = x[_ROT:_ROT + 4]
        rel = tuple(float(r / self.w_max_rad_s) ** 2 for r in rotors)
        cascade = RotorpyCascade(q, w, rs, rel, tuple(float(v) for v in x), wind)  # type: ignore[arg-type]
        return VehicleState(
            t_s=t,
            pos_ned_m=np.array([x[1], x[0], self.params.ground_z_m - x[2]], dtype=float),
            vel_ned_m_s=np.array([x[4], x[3], -x[5]], dtype=float),
            roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
            euler_rates_rad_s=_euler_rates(roll, pitch, w),
            acc_ned_m_s2=np.array([acc_enu[1], acc_enu[0], -acc_enu[2]], dtype=float),
            thrust_norm=min(1.0, max(0.0, cmd.thrust_norm)) if cmd.motors_on else 0.0,
            on_ground=on_ground,
            disturbance_ned_m_s2=self.wind_accel_ned_m_s2(x),
            cascade=cascade,
            hover_thrust_true=self.true_hover_thrust(t),
        )

    def wind_accel_ned_m_s2(self, x: np.ndarray) -> np.ndarray:
        """The acceleration the wind causes now (NED): rotorpy's body force with the air
        velocity minus the force in still air, over the mass."""
        wrench = self.derivative.body_wrench
        w_enu_flu = _rot_xyzw(x[_Q:_Q + 4])
        body_w = (float(x[_W]), float(x[_W + 1]), float(x[_W + 2]))
        rotors, v = x[_ROT:_ROT + 4], x[_V:_V + 3]
        va_wind = w_enu_flu.T @ (v - x[_WIND:_WIND + 3])
        va_still = w_enu_flu.T @ v
        f_wind, _ = wrench(body_w, rotors, (va_wind[0], va_wind[1], va_wind[2]))
        f_still, _ = wrench(body_w, rotors, (va_still[0], va_still[1], va_still[2]))
        a = w_enu_flu @ (np.asarray(f_wind) - np.asarray(f_still)) / self.mass_kg
        return np.array([a[1], a[0], -a[2]], dtype=float)


def _rot_xyzw(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion in rotorpy's x, y, z, w order."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _euler_rates(roll: float, pitch: float, w: V3) -> np.ndarray:
    """ZYX Euler rates from body rates (inverse of ``VehicleState.rates_frd_rad_s``)."""
    p, q, r = w
    sr, cr = math.sin(roll), math.cos(roll)
    cp, tp = math.cos(pitch), math.tan(pitch)
    return np.array([p + sr * tp * q + cr * tp * r, cr * q - sr * r, (sr * q + cr * r) / cp])
