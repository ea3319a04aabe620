"""PX4's multicopter attitude/rate control cascade and quad-X control allocation, as pure math
on Python floats (no numpy: a 3-vector op in numpy costs ~1 us, a float op ~30 ns, and the
cascade runs at every physics sub-step). Structure and defaults follow PX4
(docs/reference/emulator.md cites each source):

* attitude (``mc_att_control/AttitudeControl/AttitudeControl.cpp``, v1.13-v1.16): quaternion P
  law with the reduced (tilt-only) attitude, yaw de-prioritised by ``MC_YAW_WEIGHT``, the yaw-rate
  feed-forward about the world z axis, rate limits ``MC_*RATE_MAX``;
* rate (``lib/rate_control/rate_control.cpp``): ``torque = P e + I_int - D dw/dt + FF w_sp``, the
  integrator frozen on the ground, reduced for large errors (``i_factor``), frozen in the
  direction the allocator reports saturated, clamped to ``MC_*R_INT_LIM``;
* allocation (``control_allocation/.../ControlAllocationSequentialDesaturation.cpp``,
  ``mixAirmodeDisabled``): quad X with PX4's normalisation (roll/pitch 0.707, yaw 1, thrust 1),
  thrust only reduced, roll/pitch reduced, yaw mixed last with a 15 % margin;
* thrust curve (``mixer_module/functions/FunctionMotors.hpp``, ``THR_MDL_FAC``): the motor
  command that makes ``rel_thrust = f u^2 + (1 - f) u`` equal the allocated value.

Quaternions are tuples (w, x, y, z), body FRD relative to NED; vectors are tuples (x, y, z) in
body FRD unless named ``_ned``. Rates in rad/s; torques and thrust normalised (PX4's -1..1, 0..1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Quat = tuple[float, float, float, float]
V3 = tuple[float, float, float]

# Quad X rotors in PX4's order (1 front-right, 2 rear-left, 3 front-left, 4 rear-right):
# roll, pitch, yaw and thrust scales of the normalised mixer (PX4's quad_x geometry).
_S = 0.7071067811865476
QUAD_X_ROLL = (-_S, _S, _S, -_S)
QUAD_X_PITCH = (_S, -_S, _S, -_S)
QUAD_X_YAW = (1.0, 1.0, -1.0, -1.0)
# rotor positions in units of the arm's x/y offset d: (x, y) FRD
QUAD_X_POS = ((1.0, 1.0), (-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0))
MINIMUM_YAW_MARGIN = 0.15


@dataclass(frozen=True)
class Px4Gains:
    """PX4 parameters of the cascade (names after PX4's, rates in rad/s)."""

    att_p: V3 = (6.5, 6.5, 2.8)  # MC_ROLL_P, MC_PITCH_P, MC_YAW_P (1/s)
    yaw_weight: float = 0.4  # MC_YAW_WEIGHT
    rate_max_rad_s: V3 = (math.radians(220.0), math.radians(220.0), math.radians(200.0))
    rate_p: V3 = (0.15, 0.15, 0.2)  # MC_ROLLRATE_P, MC_PITCHRATE_P, MC_YAWRATE_P
    rate_i: V3 = (0.2, 0.2, 0.1)  # MC_*RATE_I
    rate_d: V3 = (0.003, 0.003, 0.0)  # MC_*RATE_D
    rate_ff: V3 = (0.0, 0.0, 0.0)  # MC_*RATE_FF
    rate_k: V3 = (1.0, 1.0, 1.0)  # MC_*RATE_K (scales P, I, D)
    rate_int_lim: V3 = (0.3, 0.3, 0.3)  # MC_RR_INT_LIM, MC_PR_INT_LIM, MC_YR_INT_LIM
    thr_mdl_fac: float = 0.0  # THR_MDL_FAC
    dgyro_cutoff_hz: float = 30.0  # IMU_DGYRO_CUTOFF (D-term derivative filter)

    def __post_init__(self) -> None:
        if not 0 <= self.yaw_weight <= 1:
            raise ValueError("mc_yaw_weight: must be in [0, 1]")
        if not 0 <= self.thr_mdl_fac <= 1:
            raise ValueError("thr_mdl_fac: must be in [0, 1]")
        for name in (
            "att_p",
            "rate_max_rad_s",
            "rate_p",
            "rate_i",
            "rate_d",
            "rate_ff",
            "rate_k",
            "rate_int_lim",
        ):
            if any(not (math.isfinite(v) and v >= 0) for v in getattr(self, name)):
                raise ValueError(f"{name}: every entry must be finite and >= 0")

    @property
    def att_p_effective(self) -> V3:
        """PX4's ``setProportionalGain``: the yaw gain divided by the yaw weight."""
        p = self.att_p
        yw = self.yaw_weight
        return (p[0], p[1], p[2] / yw if yw > 1e-4 else p[2])


# --------------------------------------------------------------------------------------------
# Quaternion helpers on tuples
def qmul(a: Quat, b: Quat) -> Quat:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def qinv(q: Quat) -> Quat:
    """Inverse of a unit quaternion (its conjugate)."""
    return (q[0], -q[1], -q[2], -q[3])


def qcanonical(q: Quat) -> Quat:
    """The representative with a non-negative real part (PX4 ``canonical()``)."""
    for v in q:
        if v != 0.0:
            return q if v > 0 else (-q[0], -q[1], -q[2], -q[3])
    return q


def qnormalize(q: Quat) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def dcm_z(q: Quat) -> V3:
    """Third column of R(q) (body z axis in NED)."""
    w, x, y, z = q
    return (2 * (x * z + w * y), 2 * (y * z - w * x), w * w - x * x - y * y + z * z)


def world_z_in_body(q: Quat) -> V3:
    """Third row of R(q): the world z axis in body axes (PX4 ``q.inversed().dcm_z()``)."""
    w, x, y, z = q
    return (2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z)


def quat_between(src: V3, dst: V3) -> Quat | None:
    """Shortest rotation taking ``src`` to ``dst`` (PX4 matrix ``Quaternion(src, dst)``); None in
    the antiparallel corner case."""
    cx = src[1] * dst[2] - src[2] * dst[1]
    cy = src[2] * dst[0] - src[0] * dst[2]
    cz = src[0] * dst[1] - src[1] * dst[0]
    d = src[0] * dst[0] + src[1] * dst[1] + src[2] * dst[2]
    if math.sqrt(cx * cx + cy * cy + cz * cz) < 1e-5 and d < 0:
        return None
    n2 = (src[0] ** 2 + src[1] ** 2 + src[2] ** 2) * (dst[0] ** 2 + dst[1] ** 2 + dst[2] ** 2)
    return qnormalize((d + math.sqrt(n2), cx, cy, cz))


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else (hi if x > hi else x)


# --------------------------------------------------------------------------------------------
def attitude_control(q: Quat, qd: Quat, yawspeed_ff_rad_s: float, gains: Px4Gains) -> V3:
    """PX4 ``AttitudeControl::update``: body rate setpoint (rad/s, FRD) from the attitude ``q``,
    the setpoint ``qd`` and the yaw-rate feed-forward about the world z axis."""
    yw = gains.yaw_weight
    p = gains.att_p_effective
    qd_red_q = quat_between(dcm_z(q), dcm_z(qd))
    if qd_red_q is None or abs(qd_red_q[1]) > 1 - 1e-5 or abs(qd_red_q[2]) > 1 - 1e-5:
        qd_red = qd
    else:
        qd_red = qmul(qd_red_q, q)
    q_mix = qcanonical(qmul(qinv(qd_red), qd))
    mw = _clamp(q_mix[0], -1.0, 1.0)
    mz = _clamp(q_mix[3], -1.0, 1.0)
    qd_w = qmul(qd_red, (math.cos(yw * math.acos(mw)), 0.0, 0.0, math.sin(yw * math.asin(mz))))
    qe = qcanonical(qmul(qinv(q), qd_w))
    rate = [2.0 * qe[1] * p[0], 2.0 * qe[2] * p[1], 2.0 * qe[3] * p[2]]
    if math.isfinite(yawspeed_ff_rad_s) and yawspeed_ff_rad_s != 0.0:
        zb = world_z_in_body(q)
        rate = [rate[i] + zb[i] * yawspeed_ff_rad_s for i in range(3)]
    lim = gains.rate_max_rad_s
    return (
        _clamp(rate[0], -lim[0], lim[0]),
        _clamp(rate[1], -lim[1], lim[1]),
        _clamp(rate[2], -lim[2], lim[2]),
    )


@dataclass(frozen=True)
class RateState:
    """The rate controller's memory: integrator (normalised torque), filtered angular
    acceleration (rad/s^2) and the previous gyro sample (rad/s)."""

    integral: V3 = (0.0, 0.0, 0.0)
    ang_acc_rad_s2: V3 = (0.0, 0.0, 0.0)
    prev_rates_rad_s: V3 = (0.0, 0.0, 0.0)
    sat_pos: tuple[bool, bool, bool] = (False, False, False)
    sat_neg: tuple[bool, bool, bool] = (False, False, False)


def rate_control(
    rates: V3, rates_sp: V3, state: RateState, dt_s: float, landed: bool, gains: Px4Gains
) -> tuple[V3, RateState]:
    """PX4 ``RateControl::update`` with the gyro-derivative filter of ``IMU_DGYRO_CUTOFF``:
    normalised torque (roll, pitch, yaw) and the next state. Saturation flags in ``state`` come
    from the previous allocation (PX4's ``control_allocator_status``)."""
    alpha = (
        1.0 - math.exp(-2.0 * math.pi * gains.dgyro_cutoff_hz * dt_s)
        if gains.dgyro_cutoff_hz > 0
        else 1.0
    )
    a0, w0 = state.ang_acc_rad_s2, state.prev_rates_rad_s
    acc = (
        a0[0] + alpha * ((rates[0] - w0[0]) / dt_s - a0[0]),
        a0[1] + alpha * ((rates[1] - w0[1]) / dt_s - a0[1]),
        a0[2] + alpha * ((rates[2] - w0[2]) / dt_s - a0[2]),
    )
    torque = []
    integral = list(state.integral)
    for i in range(3):
        k = gains.rate_k[i]
        err = rates_sp[i] - rates[i]
        torque.append(
            k * gains.rate_p[i] * err
            + integral[i]
            - k * gains.rate_d[i] * acc[i]
            + gains.rate_ff[i] * rates_sp[i]
        )
        if not landed:
            e = err
            if state.sat_pos[i]:
                e = min(e, 0.0)
            if state.sat_neg[i]:
                e = max(e, 0.0)
            f = e / math.radians(400.0)
            i_factor = max(0.0, 1.0 - f * f)
            ri = integral[i] + i_factor * k * gains.rate_i[i] * e * dt_s
            if math.isfinite(ri):
                lim = gains.rate_int_lim[i]
                integral[i] = _clamp(ri, -lim, lim)
    new = RateState(
        (integral[0], integral[1], integral[2]),
        (acc[0], acc[1], acc[2]),
        rates,
        state.sat_pos,
        state.sat_neg,
    )
    return (torque[0], torque[1], torque[2]), new


# --------------------------------------------------------------------------------------------
def _desat_gain(vec: tuple[float, ...], u: list[float], lo: float, hi: float) -> float:
    k_min = k_max = 0.0
    for i in range(4):
        v = vec[i]
        if abs(v) < 1e-7:
            continue
        if u[i] < lo:
            k = (lo - u[i]) / v
            k_min, k_max = min(k_min, k), max(k_max, k)
        if u[i] > hi:
            k = (hi - u[i]) / v
            k_min, k_max = min(k_min, k), max(k_max, k)
    return k_min + k_max


def _desaturate(
    u: list[float],
    vec: tuple[float, ...],
    lo: float = 0.0,
    hi: float = 1.0,
    reduce_only: bool = False,
) -> None:
    """PX4 ``desaturateActuators``: move along ``vec`` to minimise saturation (in place)."""
    k = _desat_gain(vec, u, lo, hi)
    if reduce_only and k > 0:
        return
    for i in range(4):
        u[i] += k * vec[i]
    k = 0.5 * _desat_gain(vec, u, lo, hi)
    for i in range(4):
        u[i] += k * vec[i]


_THRUST = (1.0, 1.0, 1.0, 1.0)


def allocate(torque: V3, thrust: float) -> tuple[list[float], V3]:
    """Quad-X allocation with airmode disabled: motor outputs (0..1, before the thrust curve)
    and the unallocated torque (set - achieved, normalised), whose signs give the rate
    controller's saturation flags."""
    r, p, y = torque
    a, b = _S * r, _S * p
    u = [thrust - a + b, thrust + a - b, thrust + a + b, thrust - a - b]
    if min(u) < 0.0 or max(u) > 1.0:  # (desaturation gains are all zero otherwise)
        _desaturate(u, _THRUST, reduce_only=True)
        _desaturate(u, QUAD_X_ROLL)
        _desaturate(u, QUAD_X_PITCH)
    u = [u[0] + y, u[1] + y, u[2] - y, u[3] - y]
    if min(u) < 0.0 or max(u) > 1.0:
        _desaturate(u, QUAD_X_YAW, hi=1.0 + MINIMUM_YAW_MARGIN)
        _desaturate(u, _THRUST, reduce_only=True)
        u = [_clamp(v, 0.0, 1.0) for v in u]
    # achieved torque: the mixer's pseudo-inverse (sum s_i u_i / sum s_i^2)
    ar = _S * (-u[0] + u[1] + u[2] - u[3]) / 2.0
    ap = _S * (u[0] - u[1] + u[2] - u[3]) / 2.0
    ay = (u[0] + u[1] - u[2] - u[3]) / 4.0
    return u, (r - ar, p - ap, y - ay)


def saturation_flags(unallocated: V3) -> tuple[tuple[bool, bool, bool], tuple[bool, bool, bool]]:
    """PX4 MulticopterRateControl: positive/negative saturation per axis from the unallocated
    torque."""
    eps = 1e-6
    pos = (unallocated[0] > eps, unallocated[1] > eps, unallocated[2] > eps)
    neg = (unallocated[0] < -eps, unallocated[1] < -eps, unallocated[2] < -eps)
    return pos, neg


def thrust_curve(u: float, factor: float) -> float:
    """Relative static thrust of a motor at relative command ``u``: ``f u^2 + (1 - f) u``."""
    return factor * u * u + (1.0 - factor) * u


def thrust_curve_inverse(rel_thrust: float, factor: float) -> float:
    """PX4 ``FunctionMotors::updateValues``: the command giving ``rel_thrust`` under the model
    ``f u^2 + (1 - f) u`` (identity for ``f = 0``)."""
    if factor <= 1e-7 or rel_thrust <= 0.0:
        return max(0.0, rel_thrust) if factor <= 1e-7 else 0.0
    b = 1.0 - factor
    t1 = b / (2.0 * factor)
    return -t1 + math.sqrt(t1 * t1 + rel_thrust / factor)
