"""Spec 5: from the RMPC input u to the attitude/thrust setpoint, checked by its physics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.config import load_config
from companion.core.errors import CoreError
from companion.core.geometry import (
    euler_zyx_from_quat,
    quat_from_euler_zyx,
    rot_z,
    rotation_from_quat,
)
from companion.core.setpoint import (
    AttitudeSetpoint,
    SetpointError,
    attitude_setpoint,
    attitude_setpoint_from_config,
    hover_setpoint,
    input_in_reference_frame,
    yaw_reference,
)

G = 9.81
LIM = dict(hover_thrust=0.5, thrust_min=0.05, thrust_max=0.95, g_m_s2=G)

acc = st.floats(-6, 6)
yaw = st.floats(-math.pi, math.pi)


@given(r1=acc, r2=acc, r3=st.floats(-6, 6), psidot=st.floats(-1, 1), psi=yaw,
       dt=st.floats(0, 0.2))
def test_thrust_axis_realises_the_commanded_specific_force(
    r1: float, r2: float, r3: float, psidot: float, psi: float, dt: float
) -> None:
    sp = attitude_setpoint([r1, r2, r3, psidot], psi, dt, **LIM)
    f_v = np.array([r1, r2, r3 - G])
    # Body -z (the thrust direction) scaled by |f| is the specific force, rotated to NED by
    # the new yaw: R(q) [0, 0, -|f|] = Rz(psi_d) f.
    np.testing.assert_allclose(
        rotation_from_quat(sp.q_wxyz) @ [0, 0, -np.linalg.norm(f_v)], rot_z(sp.yaw_rad) @ f_v,
        atol=1e-10,
    )
    assert -math.pi < sp.yaw_rad <= math.pi
    assert math.remainder(sp.yaw_rad - psi - psidot * dt, 2 * math.pi) == pytest.approx(
        0, abs=1e-12
    )
    assert sp.yaw_rate_rad_s == psidot
    phi, theta, psi_d = euler_zyx_from_quat(sp.q_wxyz)
    assert (phi, theta) == pytest.approx((sp.roll_rad, sp.pitch_rad), abs=1e-9)
    assert math.remainder(psi_d - sp.yaw_rad, 2 * math.pi) == pytest.approx(0, abs=1e-9)
    assert LIM["thrust_min"] <= sp.thrust_norm <= LIM["thrust_max"]


@given(r=st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)), psi=yaw)
def test_emulator_model_flies_the_commanded_acceleration(
    r: tuple[float, float, float], psi: float
) -> None:
    """px4-offboard.md's model a_NED = R(q)[0, 0, -g T/T_hover] + [0, 0, g] gives back
    Rz(psi_d) r: the commanded acceleration in v, in NED (unclamped inside u_max)."""
    sp = attitude_setpoint([*r, 0.0], psi, 0.05, **LIM)
    assert not sp.thrust_clamped
    a_ned = rotation_from_quat(sp.q_wxyz) @ [0, 0, -G * sp.thrust_norm / 0.5] + [0, 0, G]
    np.testing.assert_allclose(a_ned, rot_z(psi) @ np.asarray(r), atol=1e-10)


def test_known_values() -> None:
    sp = attitude_setpoint([0, 0, 0, 0], 0.3, 0.05, **LIM)
    assert sp.thrust_norm == pytest.approx(0.5, abs=1e-15)
    np.testing.assert_allclose(sp.q_wxyz, quat_from_euler_zyx(0, 0, 0.3), atol=1e-15)
    # Forward acceleration: nose down (negative FRD pitch); rightward: right roll.
    fwd = attitude_setpoint([1.0, 0, 0, 0], 0.0, 0.05, **LIM)
    assert fwd.pitch_rad == pytest.approx(-math.atan(1.0 / G)) and fwd.roll_rad == 0.0
    right = attitude_setpoint([0, 1.0, 0, 0], 0.0, 0.05, **LIM)
    assert right.roll_rad == pytest.approx(math.asin(1.0 / math.hypot(1.0, G)))
    # Climb (r3 < 0 is up): more thrust.
    up = attitude_setpoint([0, 0, -1.0, 0], 0.0, 0.05, **LIM)
    assert up.thrust_norm == pytest.approx(0.5 * (G + 1.0) / G)
    # Yaw: psi_d = psi + psidot dt, wrapped.
    yw = attitude_setpoint([0, 0, 0, 0.3], math.pi - 0.005, 0.05, **LIM)
    assert yw.yaw_rad == pytest.approx(-math.pi + 0.01)
    s = math.sqrt(0.5)
    np.testing.assert_allclose(
        attitude_setpoint([0, 0, 0, 0], math.pi / 2, 0.0, **LIM).q_wxyz, [s, 0, 0, s], atol=1e-15
    )


def test_thrust_clamps() -> None:
    hi = attitude_setpoint([0, 0, -12.0, 0], 0.0, 0.05, **LIM)
    assert hi.thrust_norm == 0.95 and hi.thrust_clamped
    assert hi.specific_force_m_s2 == pytest.approx(G + 12.0)
    lo = attitude_setpoint([0, 0, 9.5, 0], 0.0, 0.05, **LIM)
    assert lo.thrust_norm == 0.05 and lo.thrust_clamped
    mid = attitude_setpoint([0.5, 0.5, 0.5, 0], 0.0, 0.05, **LIM)
    assert not mid.thrust_clamped and 0.05 < mid.thrust_norm < 0.95


BAD = [math.nan, math.inf, -math.inf]


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("i", range(4))
def test_non_finite_input_is_refused(bad: float, i: int) -> None:
    u = [0.1, -0.2, 0.3, 0.05]
    u[i] = bad
    with pytest.raises(SetpointError) as exc:
        attitude_setpoint(u, 0.0, 0.05, **LIM)
    assert isinstance(exc.value, CoreError)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("key", ["yaw_rad", "dt_s", "hover_thrust", "g_m_s2"])
def test_non_finite_parameters_are_refused(bad: float, key: str) -> None:
    args = {"yaw_rad": 0.0, "dt_s": 0.05, **LIM, key: bad}
    with pytest.raises(SetpointError):
        attitude_setpoint([0, 0, 0, 0], **args)


def test_impossible_commands_are_refused() -> None:
    with pytest.raises(SetpointError):
        attitude_setpoint([0, 0, G, 0], 0.0, 0.05, **LIM)  # no upward thrust
    with pytest.raises(SetpointError):
        attitude_setpoint([0, 0, 0], 0.0, 0.05, **LIM)
    with pytest.raises(SetpointError):
        attitude_setpoint([0, 0, 0, 0], 0.0, 0.05, hover_thrust=0.5, thrust_min=0.6,
                          thrust_max=0.9)


def test_from_config_and_hover() -> None:
    cfg = load_config()
    a = attitude_setpoint_from_config([0.3, -0.2, 0.1, 0.2], 1.0, cfg.control, cfg.rmpc)
    b = attitude_setpoint([0.3, -0.2, 0.1, 0.2], 1.0, cfg.rmpc.dt_s,
                          hover_thrust=cfg.control.hover_thrust,
                          thrust_min=cfg.control.thrust_min, thrust_max=cfg.control.thrust_max,
                          g_m_s2=cfg.rmpc.g_m_s2)
    assert isinstance(a, AttitudeSetpoint)
    np.testing.assert_array_equal(a.q_wxyz, b.q_wxyz)
    assert a.thrust_norm == b.thrust_norm
    h = hover_setpoint(0.7, hover_thrust=0.4, thrust_min=0.1, thrust_max=0.9)
    assert h.thrust_norm == pytest.approx(0.4) and h.yaw_rad == 0.7 and h.yaw_rate_rad_s == 0.0
    with pytest.raises(ValueError):
        h.q_wxyz[0] = 0.0


@given(r=st.tuples(st.floats(-2.4, 2.4), st.floats(-2.4, 2.4), st.floats(-2.4, 2.4)),
       psidot=st.floats(-0.8, 0.8), psi=yaw, lead=st.floats(-0.6, 0.6))
def test_setpoint_on_a_yaw_reference_flies_the_acceleration_of_the_measured_frame(
    r: tuple[float, float, float], psidot: float, psi: float, lead: float
) -> None:
    """The controller's r is in the frame of the measured yaw ``psi``; the setpoint is built on
    a yaw reference ``lead`` ahead of it (the integrated previous setpoint). Re-expressed, the
    NED acceleration flown is Rz(psi) r whatever the lead (dt 0: the spec's own psidot dt turn
    is a separate matter); as sent, it would be turned by the lead."""
    ref = psi + lead
    u = input_in_reference_frame([*r, psidot], psi, ref)
    assert u[2] == r[2] and u[3] == psidot
    sp = attitude_setpoint(u, ref, 0.0, **LIM)
    assert not sp.thrust_clamped
    a_ned = rotation_from_quat(sp.q_wxyz) @ [0, 0, -G * sp.thrust_norm / 0.5] + [0, 0, G]
    np.testing.assert_allclose(a_ned, rot_z(psi) @ np.asarray(r), atol=1e-9)


def test_yaw_reference_frame_known_value_and_bad_input() -> None:
    # r = 1 m/s^2 forward in the measured frame; the reference leads by +90 deg: forward of the
    # measured frame is the reference frame's -y (left)
    u = input_in_reference_frame([1.0, 0.0, 0.0, 0.3], 0.0, math.pi / 2)
    np.testing.assert_allclose(u, [0.0, -1.0, 0.0, 0.3], atol=1e-12)
    with pytest.raises(SetpointError):
        input_in_reference_frame([1.0, 0.0, 0.0], 0.0, 0.1)
    with pytest.raises(SetpointError):
        input_in_reference_frame([1.0, 0.0, 0.0, 0.0], math.nan, 0.1)


def _yaw_rate_flown(rate_cmd: float, yaw_p: float = 2.8, seconds: float = 6.0) -> float:
    """The yaw rate a first-order yaw loop (PX4's MC_YAW_P) achieves behind setpoints built
    on :func:`yaw_reference` at 20 Hz, measured over the last 2 s."""
    dt, sub = 0.05, 20
    yaw, sp = 0.0, None
    log = []
    for _ in range(int(seconds / dt)):
        ref = yaw_reference(sp, yaw, 0.4)
        sp = ref + rate_cmd * dt
        for _step in range(sub):  # the vehicle between two setpoints
            yaw += yaw_p * math.remainder(sp - yaw, 2 * math.pi) * dt / sub
        log.append(yaw)
    n = int(2.0 / dt)
    return (log[-1] - log[-1 - n]) / (n * dt)


@pytest.mark.parametrize("rate", [0.3, 0.5, 0.84, -0.84])
def test_yaw_reference_lets_a_lagging_yaw_loop_fly_the_commanded_rate(rate: float) -> None:
    """Behind PX4's yaw loop (lag rate / 2.8: 0.3 rad at 0.84 rad/s) the setpoint must lead
    the measured yaw by that lag; reset to the measured yaw at 0.2 rad the achieved rate was
    0.2-0.4 rad/s whatever the command."""
    assert _yaw_rate_flown(rate) == pytest.approx(rate, rel=1e-3)


def test_yaw_reference_beyond_its_bound_still_turns_at_the_bound_s_rate() -> None:
    """Asked for more than the lead allows (1.5 rad/s needs 0.54 rad > 0.4), the clamped lead
    still drives the loop at ~2.8 x 0.4 rad/s; a reset to the measured yaw collapsed it."""
    assert _yaw_rate_flown(1.5) > 0.95 * 2.8 * 0.4


def test_yaw_reference_is_held_within_the_bound_when_the_vehicle_does_not_turn() -> None:
    yaw, sp = 1.0, None
    for _ in range(200):  # PX4 holds its own yaw (before OFFBOARD): no wind-up
        sp = yaw_reference(sp, yaw, 0.4) + 0.8 * 0.05
    assert math.remainder(sp - yaw, 2 * math.pi) == pytest.approx(0.44)
    assert yaw_reference(None, 0.3, 0.4) == 0.3
    assert yaw_reference(math.nan, 0.3, 0.4) == 0.3
    assert yaw_reference(3.0, -3.0, 0.4) == 3.0  # within the bound across +-pi
    assert yaw_reference(-3.0, 2.0, 0.4) == pytest.approx(2.4)
