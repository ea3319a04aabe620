"""A quadrotor flown by PX4's control cascade: rigid-body dynamics with inertia, four motors with
first-order dynamics, saturation and a thrust curve, and a vehicle that differs from its
parameters (true hover thrust, payload, drag, battery sag). Pure Python floats, fixed-step,
deterministic; the same interface as :class:`sim_bridge.physics.vehicle.VehicleModel`.

Each sub-step (``dt_s``, the emulator's ``physics_dt_s``) runs, as PX4 does at its gyro rate:
attitude P -> rate PID -> allocation (quad X, airmode off) -> THR_MDL_FAC inversion -> motors::

    f_i' = (c(u_i) - f_i) / tau_m,     c(u) = k u^2 + (1 - k) u   (the TRUE curve, k_true)
    F_i  = f_i F_max b(t)              F_max = m g / (4 c(inv_px4(T_hover_true)))
    m a  = R(q) [0, 0, -sum F_i] + m g e_z - m drag v + m d(t)
    I w' = tau - w x I w,              q' = q (x) (0, w) / 2

with ``b(t) = 1 - min(max_loss, loss_rate t)`` the battery's thrust factor and ``m = m_nom (1 +
mass_error)`` (payload: the motors are those of the nominal vehicle, so the true hover thrust
rises by the same factor and the inertia with it). docs/reference/emulator.md has the details.

The controller state (integrators, filtered angular acceleration, motor thrusts, the exact
quaternion and body rates) travels in ``VehicleState.cascade``, so ``step`` is a pure function.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim_bridge.physics.px4_control import (
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
from sim_bridge.physics.vehicle import (
    G_M_S2,
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleState,
    euler_from_quat,
    quat_from_euler,
)


@dataclass(frozen=True)
class AirframeParams:
    """The physical vehicle (SI units). Defaults: a 2 kg, 0.5 m quad X like PX4's x500 SITL
    model; ``km_m`` is PX4's ``CA_ROTOR*_KM`` default."""

    mass_kg: float = 2.0
    inertia_kg_m2: V3 = (0.0217, 0.0217, 0.04)
    arm_xy_m: float = 0.174  # each rotor's |x| = |y| offset from the centre of mass
    km_m: float = 0.05  # yaw moment / thrust of a rotor
    motor_tau_s: float = 0.02  # first-order motor (thrust) time constant
    true_hover_thrust: float = 0.5  # command that hovers the nominal vehicle, full battery
    motor_curve_factor: float = 0.0  # the motors' TRUE thrust curve k (PX4 assumes THR_MDL_FAC)
    mass_error: float = 0.0  # payload: true mass = mass_kg (1 + mass_error)
    drag_per_s: float = 0.05  # true linear drag a = -k v
    battery_loss_per_s: float = 0.0  # fraction of the maximum thrust lost per second of flight
    battery_max_loss: float = 0.0  # ... at most
    ground_z_m: float = 0.0
    g_m_s2: float = G_M_S2

    def __post_init__(self) -> None:
        if not (
            self.mass_kg > 0
            and all(i > 0 for i in self.inertia_kg_m2)
            and self.arm_xy_m > 0
            and self.km_m >= 0
            and self.motor_tau_s > 0
        ):
            raise ValueError("airframe: mass, inertia, arm, motor_tau_s must be > 0")
        if not 0 < self.true_hover_thrust < 1:
            raise ValueError("true_hover_thrust: must be in (0, 1)")
        if not 0 <= self.motor_curve_factor <= 1:
            raise ValueError("motor_curve_factor: must be in [0, 1]")
        if not (
            -0.5 < self.mass_error < 1.0
            and self.drag_per_s >= 0
            and self.battery_loss_per_s >= 0
            and 0 <= self.battery_max_loss < 0.9
        ):
            raise ValueError("invalid vehicle imperfections")


def battery_factor(t_s: float, loss_per_s: float, max_loss: float) -> float:
    """Fraction of the full-battery maximum thrust available at ``t_s`` (s of flight)."""
    return 1.0 - min(max_loss, loss_per_s * max(0.0, t_s))


@dataclass(frozen=True)
class CascadeState:
    """What the PX4 model remembers between steps: exact attitude and body rates, the rate
    controller's state, and each motor's relative thrust (0..1 of its maximum)."""

    q_wxyz: Quat
    rates_frd_rad_s: V3
    rate: RateState
    motors: tuple[float, float, float, float]


class Px4VehicleModel:
    """Fixed-step integrator of the PX4 cascade + rigid body. ``step(state, cmd, duration_s)``
    advances by whole ``dt_s`` sub-steps with the command held (like ``VehicleModel``)."""

    def __init__(
        self,
        gains: Px4Gains,
        airframe: AirframeParams,
        disturbance: Disturbance | None = None,
        dt_s: float = 0.0025,
    ) -> None:
        if not dt_s > 0:
            raise ValueError("dt_s must be > 0")
        self.gains = gains
        self.params = airframe
        self.disturbance = disturbance or Disturbance(DisturbanceParams())
        self.dt_s = dt_s
        a = airframe
        self.mass_kg = a.mass_kg * (1.0 + a.mass_error)
        self.inertia = tuple(i * (1.0 + a.mass_error) for i in a.inertia_kg_m2)
        hover_rel = thrust_curve(
            thrust_curve_inverse(a.true_hover_thrust, gains.thr_mdl_fac), a.motor_curve_factor
        )
        self.f_max_n = a.mass_kg * a.g_m_s2 / (4.0 * hover_rel)  # per motor, full battery
        self._motor_alpha = 1.0 - math.exp(-dt_s / a.motor_tau_s)

    # ---------------------------------------------------------------- derived figures
    def true_hover_thrust(self, t_s: float) -> float:
        """The collective thrust command that hovers the vehicle at ``t_s`` (battery, payload
        and both thrust curves included): what PX4's hover-thrust estimator converges to."""
        a = self.params
        rel = (
            self.mass_kg
            * a.g_m_s2
            / (4.0 * self.f_max_n * battery_factor(t_s, a.battery_loss_per_s, a.battery_max_loss))
        )
        if rel >= 1.0:
            return 1.0
        k = a.motor_curve_factor  # invert the true curve, then apply PX4's curve
        u = rel if k <= 1e-7 else (-(1 - k) + math.sqrt((1 - k) ** 2 + 4 * k * rel)) / (2 * k)
        return thrust_curve(u, self.gains.thr_mdl_fac)

    def initial_cascade(self, s: VehicleState) -> CascadeState:
        """Cascade state for a state that has none: the state's attitude and rates, motors at
        the hover thrust when airborne (an equilibrium), off on the ground."""
        q = tuple(float(v) for v in quat_from_euler(s.roll_rad, s.pitch_rad, s.yaw_rad))
        w = tuple(float(v) for v in s.rates_frd_rad_s)
        hover = (
            0.0
            if s.on_ground
            else self.mass_kg
            * self.params.g_m_s2
            / (
                4.0
                * self.f_max_n
                * battery_factor(
                    s.t_s, self.params.battery_loss_per_s, self.params.battery_max_loss
                )
            )
        )
        return CascadeState(q, w, RateState(prev_rates_rad_s=w), (hover,) * 4)  # type: ignore[arg-type]

    # ---------------------------------------------------------------- stepping
    def _motors(self, f: list[float], w: V3, w_sp: V3, rs: RateState, thrust_cmd: float,
                on_ground: bool) -> RateState:
        """One sub-step of PX4's rate loop, the mixer and the motors' lag: ``f`` (the motors'
        thrusts as fractions of f_max) updated in place; the rate loop's new state."""
        g, a = self.gains, self.params
        torque, rs = rate_control(w, w_sp, rs, self.dt_s, on_ground, g)
        u, unalloc = allocate(torque, thrust_cmd)
        sat_pos, sat_neg = saturation_flags(unalloc)
        if sat_pos != rs.sat_pos or sat_neg != rs.sat_neg:
            rs = RateState(rs.integral, rs.ang_acc_rad_s2, rs.prev_rates_rad_s, sat_pos, sat_neg)
        ma, thr_fac, true_fac = self._motor_alpha, g.thr_mdl_fac, a.motor_curve_factor
        for i in range(4):
            target = thrust_curve(thrust_curve_inverse(u[i], thr_fac), true_fac)
            f[i] += (target - f[i]) * ma
        return rs

    def _rotate(self, q: Quat, w: V3, forces: tuple[float, float, float, float],
                resting: bool) -> tuple[Quat, V3]:
        """One sub-step of the attitude: Euler's equations under the rotors' torques, or, when
        ``resting`` on the ground, level with no rotation (yaw kept)."""
        if resting:
            yaw = euler_from_quat(np.array(q))[2]
            level: Quat = tuple(float(v) for v in quat_from_euler(0.0, 0.0, yaw))  # type: ignore[assignment]
            return level, (0.0, 0.0, 0.0)
        f0, f1, f2, f3 = forces
        d_arm, km, dt = self.params.arm_xy_m, self.params.km_m, self.dt_s
        ixx, iyy, izz = self.inertia
        # rotors at d QUAD_X_POS with yaw signs QUAD_X_YAW (px4_control):
        # tau = sum r_i x (0, 0, -F_i) + km yaw_i F_i
        tx = -d_arm * (f0 - f1 - f2 + f3)
        ty = d_arm * (f0 - f1 + f2 - f3)
        tz = km * (f0 + f1 - f2 - f3)
        p, qq, r = w
        dp = (tx - (izz - iyy) * qq * r) / ixx
        dq = (ty - (ixx - izz) * r * p) / iyy
        dr = (tz - (iyy - ixx) * p * qq) / izz
        w = (p + dp * dt, qq + dq * dt, r + dr * dt)
        return _integrate_quat(q, w, dt), w

    def step(self, s: VehicleState, cmd: AttitudeCommand, duration_s: float) -> VehicleState:
        n = max(1, round(duration_s / self.dt_s))
        a, g, dt = self.params, self.gains, self.dt_s
        cs = s.cascade if isinstance(s.cascade, CascadeState) else self.initial_cascade(s)
        q, w, rs, f = cs.q_wxyz, cs.rates_frd_rad_s, cs.rate, list(cs.motors)
        px, py, pz = (float(v) for v in s.pos_ned_m)
        vx, vy, vz = (float(v) for v in s.vel_ned_m_s)
        on_ground = s.on_ground
        m = self.mass_kg
        grav = a.g_m_s2
        drag = a.drag_per_s
        t = s.t_s
        motors_on = cmd.motors_on
        thrust_cmd = min(1.0, max(0.0, cmd.thrust_norm)) if motors_on else 0.0
        qd: Quat = tuple(
            float(v) for v in quat_from_euler(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad)
        )  # type: ignore[assignment]
        ff = cmd.yaw_rate_ff_rad_s
        rates_sp = cmd.body_rates_frd_rad_s  # offboard rate setpoint: straight to the rate loop
        ma = self._motor_alpha
        ax = ay = az = 0.0
        dist = np.zeros(3)
        for _ in range(n):
            f_max = self.f_max_n * battery_factor(t, a.battery_loss_per_s, a.battery_max_loss)
            if motors_on:
                w_sp = rates_sp if rates_sp is not None else attitude_control(q, qd, ff, g)
                rs = self._motors(f, w, w_sp, rs, thrust_cmd, on_ground)
            else:
                for i in range(4):
                    f[i] -= f[i] * ma
            f0, f1, f2, f3 = f[0] * f_max, f[1] * f_max, f[2] * f_max, f[3] * f_max
            total = f0 + f1 + f2 + f3
            q, w = self._rotate(q, w, (f0, f1, f2, f3),
                                resting=on_ground and (total <= m * grav or not motors_on))
            qw, qx, qy, qz = q
            # body z axis in NED (third column of R): specific thrust = -total/m along it
            zx = 2 * (qx * qz + qw * qy)
            zy = 2 * (qy * qz - qw * qx)
            zz = qw * qw - qx * qx - qy * qy + qz * qz
            dist = self.disturbance.accel_ned_m_s2(t)
            sf = -total / m
            ax = sf * zx - drag * vx + float(dist[0])
            ay = sf * zy - drag * vy + float(dist[1])
            az = sf * zz + grav - drag * vz + float(dist[2])
            vx, vy, vz = vx + ax * dt, vy + ay * dt, vz + az * dt
            nx, ny, nz = px + vx * dt, py + vy * dt, pz + vz * dt  # semi-implicit Euler
            if nz >= a.ground_z_m:
                (px, py, pz), (vx, vy, vz), (ax, ay, az), on_ground = _ground_contact(
                    (px, py, pz), (nx, ny), (vx, vy, vz), (ax, ay, az), a.ground_z_m, on_ground)
            else:
                px, py, pz, on_ground = nx, ny, nz, False
            t += dt
        roll, pitch, yaw = euler_from_quat(np.array(q))
        cascade = CascadeState(q, w, rs, (f[0], f[1], f[2], f[3]))
        return VehicleState(
            t_s=t,
            pos_ned_m=np.array([px, py, pz]),
            vel_ned_m_s=np.array([vx, vy, vz]),
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            euler_rates_rad_s=_euler_rates(roll, pitch, w),
            acc_ned_m_s2=np.array([ax, ay, az]),
            thrust_norm=thrust_cmd,
            on_ground=on_ground,
            disturbance_ned_m_s2=dist,
            cascade=cascade,
            hover_thrust_true=self.true_hover_thrust(t),
        )


def _ground_contact(p_old: V3, n_xy: tuple[float, float], v: V3, acc: V3, ground_z_m: float,
                    was_on_ground: bool) -> tuple[V3, V3, V3, bool]:
    """A sub-step that ends at or below the ground: position, velocity, acceleration after the
    contact and whether the vehicle rests on it. Pushed down or still moving down it stops
    there (on the ground already: without sliding); lifting off, only its height is held."""
    if acc[2] >= 0 or v[2] >= 0:
        nx, ny = (p_old[0], p_old[1]) if was_on_ground else n_xy
        return (nx, ny, ground_z_m), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), True
    return (n_xy[0], n_xy[1], ground_z_m), v, acc, False


def _integrate_quat(q: Quat, w: V3, dt: float) -> Quat:
    """``q (x) exp(w dt / 2)``: exact for body rates ``w`` held over ``dt``."""
    p, qq, r = w
    n = math.sqrt(p * p + qq * qq + r * r)
    if n * dt < 1e-12:
        return q
    h = 0.5 * n * dt
    s = math.sin(h) / n
    return qnormalize(qmul(q, (math.cos(h), p * s, qq * s, r * s)))


def _euler_rates(roll: float, pitch: float, w: V3) -> np.ndarray:
    """ZYX Euler rates from body rates (inverse of ``VehicleState.rates_frd_rad_s``)."""
    p, q, r = w
    sr, cr = math.sin(roll), math.cos(roll)
    cp = math.cos(pitch)
    tp = math.tan(pitch)
    return np.array([p + sr * tp * q + cr * tp * r, cr * q - sr * r, (sr * q + cr * r) / cp])
