"""The PX4 state machine, driven with explicit times (no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim_bridge.physics.vehicle import (
    VehicleModel,
    VehicleParams,
    VehicleState,
    initial_state,
    quat_from_euler,
)
from sim_bridge.px4 import (
    ACCEPTED,
    STATE_ACTIVE,
    STATE_CRITICAL,
    STATE_FLIGHT_TERMINATION,
    STATE_STANDBY,
    TEMPORARILY_REJECTED,
    UNSUPPORTED,
    AttitudeTarget,
    Mode,
    Px4,
    Px4Params,
)

DT = 0.05


class Rig:
    """PX4 + physics stepped in simulated time."""

    def __init__(self, airborne: bool = True, **params: float) -> None:
        self.model = VehicleModel(VehicleParams(ground_z_m=0.3), dt_s=0.0025)
        self.s: VehicleState = (initial_state((0, 0, -3.2), yaw_rad=0.4) if airborne
                                else initial_state((0, 0, 0.3), on_ground=True))
        self.px4 = Px4(Px4Params(**params), self.s, armed=airborne)  # type: ignore[arg-type]
        self.t = 0.0

    def run(self, seconds: float, sp: AttitudeTarget | None = None) -> None:
        for _ in range(round(seconds / DT)):
            if sp is not None:
                self.px4.on_attitude_target(self.t, sp)
            self.px4.update(self.t, self.s)
            self.s = self.model.step(self.s, self.px4.attitude_command(), DT)
            self.t = round(self.t + DT, 9)
        self.px4.update(self.t, self.s)

    def cmd(self, command: int, *p: float) -> int:
        return self.px4.handle_command(self.t, command, tuple(p)).result


def att(roll: float = 0.0, yaw: float = 0.4, thrust: float = 0.5, mask: int = 7
        ) -> AttitudeTarget:
    q = quat_from_euler(roll, 0.0, yaw)
    return AttitudeTarget(mask, tuple(float(v) for v in q), (0.0, 0.0, 0.0), thrust)


def test_heartbeat_encoding_matches_px4() -> None:
    r = Rig(airborne=False)
    assert (r.px4.base_mode, r.px4.custom_mode) == (81, 3 << 16)  # disarmed POSCTL
    r.run(1.0, att())
    assert r.cmd(176, 1, 6, 0) == ACCEPTED
    assert r.cmd(400, 1) == ACCEPTED
    assert (r.px4.base_mode, r.px4.custom_mode) == (145, 393216)  # armed OFFBOARD
    assert r.cmd(176, 1, 4, 3) == ACCEPTED
    assert r.px4.mode is Mode.AUTO_LOITER
    assert (r.px4.base_mode, r.px4.custom_mode) == (128 | 29, (4 << 16) | (3 << 24))


def test_offboard_applies_setpoints_only_in_offboard() -> None:
    r = Rig()
    r.run(1.0, att(roll=0.2))
    assert abs(r.s.roll_rad) < 1e-3  # POSCTL: a signal, but not applied
    assert r.px4.signal_fresh(r.t)
    assert r.cmd(176, 1, 6, 0) == ACCEPTED
    r.run(0.5, att(roll=0.2, thrust=0.5 / math.cos(0.2)))
    assert math.isclose(r.s.roll_rad, 0.2, abs_tol=1e-3)


def test_offboard_is_judged_on_the_last_health_check() -> None:
    """PX4 judges a DO_SET_MODE on its last health check (10 Hz, Commander::run), but a
    setpoint arriving while that check said "signal lost" makes it check again at once
    (Commander::offboardControlCheck): a request right behind the first setpoint is accepted,
    one that overtakes it is refused, and never on a signal lost since the check."""
    r = Rig()
    r.run(0.3)  # hovering, no setpoint yet: the checks at 0, 0.1, 0.2, 0.3 saw none
    assert r.px4.handle_command(r.t + 0.005, 176, (1, 6, 0)).result == TEMPORARILY_REJECTED
    assert not r.px4.signal_checked
    r.px4.on_attitude_target(r.t + 0.01, att())
    assert r.px4.handle_command(r.t + 0.01, 176, (1, 6, 0)).result == ACCEPTED
    assert r.px4.mode is Mode.OFFBOARD
    # a verdict of "fresh" does not outlive the signal itself
    r2 = Rig(com_of_loss_t_s=0.5)
    r2.px4.on_attitude_target(0.0, att())
    r2.px4.update(0.45, r2.s)
    assert r2.px4.signal_checked  # the check at 0.45 s saw a fresh signal; it is lost at 0.5 s
    assert r2.px4.handle_command(0.52, 176, (1, 6, 0)).result == TEMPORARILY_REJECTED
    # a fresh verdict is not re-checked by every setpoint: only the 10 Hz checks renew it
    r3 = Rig(com_of_loss_t_s=0.5)
    r3.px4.on_attitude_target(0.0, att())
    r3.px4.update(0.0, r3.s)
    check_t_s = r3.px4._check_t_s
    r3.px4.on_attitude_target(0.05, att())
    assert r3.px4._check_t_s == check_t_s


@pytest.mark.parametrize(("act", "mode", "armed"), [
    (0, Mode.POSCTL, True), (1, Mode.ALTCTL, True), (2, Mode.STABILIZED, True),
    (3, Mode.AUTO_RTL, True), (4, Mode.AUTO_LAND, True), (5, Mode.AUTO_LOITER, True),
    (6, Mode.TERMINATION, True), (7, Mode.POSCTL, False)])
def test_offboard_loss_switches_to_com_obl_rc_act_at_once(act: int, mode: Mode,
                                                          armed: bool) -> None:
    r = Rig(com_obl_rc_act=act, com_of_loss_t_s=0.5)
    r.run(1.0, att())
    assert r.cmd(176, 1, 6, 0) == ACCEPTED
    r.run(0.5, att())
    t_last = r.t - DT
    # silence: still OFFBOARD up to COM_OF_LOSS_T, then the failsafe mode
    for _ in range(9):
        r.run(DT)
        assert r.px4.mode is Mode.OFFBOARD, r.t - t_last
    r.run(DT)
    assert math.isclose(r.t - t_last, 0.5 + DT)
    if mode is Mode.AUTO_RTL:  # already above home: RTL goes straight on to landing
        assert r.px4.mode in (Mode.AUTO_RTL, Mode.AUTO_LAND) and r.px4.armed
        assert any("OFFBOARD -> AUTO.RTL" in e for e in r.px4.events)
    else:
        assert r.px4.mode is mode and r.px4.armed is armed
    # HEARTBEAT system_status as PX4's HEARTBEAT.hpp: CRITICAL while the failsafe action is in
    # force (armed), STANDBY once disarmed, FLIGHT_TERMINATION for Terminate
    expected = {6: STATE_FLIGHT_TERMINATION, 7: STATE_STANDBY}.get(act, STATE_CRITICAL)
    assert r.px4.system_status == expected
    assert r.px4.failsafe is (act != 7)
    if act in (6, 7):
        return
    # the failsafe holds until a client asks for a mode: then ACTIVE again
    r.run(0.2)
    assert r.px4.system_status == STATE_CRITICAL
    assert r.cmd(176, 1, 3, 0) == ACCEPTED  # Position
    assert r.px4.system_status == STATE_ACTIVE and not r.px4.failsafe


def test_throttle_ignore_is_not_a_signal() -> None:
    r = Rig()
    sp = att(roll=0.3, mask=7 | 64)
    assert not sp.is_signal
    r.run(1.0, sp)
    assert not r.px4.signal_fresh(r.t)
    assert r.cmd(176, 1, 6, 0) == TEMPORARILY_REJECTED
    assert r.px4.ignored_setpoints == 20
    # NaN attitude, or attitude and rates both ignored: no signal either
    assert not AttitudeTarget(7, (math.nan, 0, 0, 0), (0, 0, 0), 0.5).is_signal
    assert not AttitudeTarget(128 | 3, (1, 0, 0, 0), (0, 0, 0), 0.5).is_signal
    assert AttitudeTarget(128, (0, 0, 0, 0), (0.1, 0, 0), 0.5).is_signal  # rates only


def test_body_rate_setpoints_integrate() -> None:
    r = Rig()
    r.run(1.0, att())
    assert r.cmd(176, 1, 6, 0) == ACCEPTED
    r.run(1.0, AttitudeTarget(128, (1, 0, 0, 0), (0.0, 0.0, 0.2), 0.5))
    assert math.isclose(r.s.yaw_rad, 0.4 + 0.2 * 1.0, abs_tol=0.03)


def test_arming_rules() -> None:
    r = Rig(airborne=False)
    assert r.cmd(400, 1) == ACCEPTED  # POSCTL on the ground
    assert r.cmd(400, 0) == ACCEPTED
    assert r.cmd(176, 1, 6, 0) == ACCEPTED  # disarmed: OFFBOARD accepted
    assert r.cmd(400, 1) == TEMPORARILY_REJECTED  # no signal
    assert r.cmd(400, 1, 21196) == ACCEPTED  # forced
    assert r.cmd(400, 2) == UNSUPPORTED
    assert r.cmd(400, math.nan) == UNSUPPORTED
    air = Rig()
    assert air.cmd(400, 0) == TEMPORARILY_REJECTED  # not landed
    assert air.cmd(400, 0, 21196) == ACCEPTED and not air.px4.armed
    assert air.cmd(12345) == UNSUPPORTED


def test_auto_disarm_without_takeoff_after_com_disarm_prflt() -> None:
    r = Rig(airborne=False, com_disarm_prflt_s=10.0)
    assert r.cmd(400, 1) == ACCEPTED
    r.run(9.9)
    assert r.px4.armed
    r.run(0.15)
    assert not r.px4.armed


def test_takeoff_hold_land_disarm() -> None:
    r = Rig(airborne=False)
    assert r.cmd(400, 1) == ACCEPTED
    assert r.cmd(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan) == ACCEPTED
    assert r.px4.mode is Mode.AUTO_TAKEOFF and r.px4.landed_state == 1
    r.run(8.0)
    assert r.px4.mode is Mode.AUTO_LOITER
    assert math.isclose(r.s.pos_ned_m[2], 0.3 - 2.5, abs_tol=0.2)
    assert r.px4.landed_state == 2
    assert r.cmd(21) == ACCEPTED
    while not r.px4.landed:
        assert r.t < 30.0
        r.run(DT)
    t_land = r.t
    assert 2.2 / 0.7 - 0.5 < t_land - 8.0 < 2.2 / 0.7 + 1.5  # MPC_LAND_SPEED 0.7 m/s
    while r.px4.armed:
        r.run(DT)
    assert math.isclose(r.t - t_land, 2.0, abs_tol=DT + 1e-9)  # COM_DISARM_LAND


def test_position_hold_rejects_a_push() -> None:
    r = Rig()
    r.s = VehicleState(t_s=r.s.t_s, pos_ned_m=r.s.pos_ned_m, vel_ned_m_s=np.array([1.0, 0, 0]),
                       roll_rad=0, pitch_rad=0, yaw_rad=0.4)
    r.run(8.0)
    assert abs(r.s.pos_ned_m[0]) < 0.05 and abs(r.s.pos_ned_m[2] + 3.2) < 0.05


def test_rtl_returns_home_and_lands() -> None:
    r = Rig()
    r.run(1.0, att())
    assert r.cmd(176, 1, 6, 0) == ACCEPTED
    r.run(1.5, att(roll=0.15, thrust=0.5 / math.cos(0.15)))
    assert r.cmd(20) == ACCEPTED
    r.run(25.0)
    assert r.px4.landed
    assert math.hypot(r.s.pos_ned_m[0], r.s.pos_ned_m[1]) < 0.6


@pytest.mark.parametrize(("p1", "p2", "p3", "mode"), [
    (1, 1, 0, Mode.MANUAL), (1, 2, 0, Mode.ALTCTL), (1, 3, 0, Mode.POSCTL),
    (1, 5, 0, Mode.ACRO), (1, 7, 0, Mode.STABILIZED), (1, 4, 3, Mode.AUTO_LOITER),
    (1, 4, 5, Mode.AUTO_RTL), (1, 4, 6, Mode.AUTO_LAND),
    (64 | 16 | 8, 0, 0, Mode.POSCTL), (64 | 16, 0, 0, Mode.STABILIZED), (64, 0, 0, Mode.MANUAL),
    (129, 3, 0, Mode.POSCTL),  # MAVSDK sets the armed flag too when armed
])
def test_do_set_mode_forms(p1: float, p2: float, p3: float, mode: Mode) -> None:
    r = Rig()
    start = Mode.ALTCTL if mode is Mode.STABILIZED else Mode.STABILIZED
    assert r.cmd(176, 1, start.value[0], 0) == ACCEPTED  # so that each case is a change
    assert r.cmd(176, p1, p2, p3) == ACCEPTED
    assert r.px4.mode is mode
    main, sub = mode.value
    assert r.px4.custom_mode == (main << 16) | (sub << 24)


@pytest.mark.parametrize(("p1", "p2", "p3"), [
    (1, 4, 4),  # AUTO.MISSION without a mission
    (1, 9, 0), (1, math.nan, 0), (math.nan, 3, 0), (4, 0, 0), (0, 0, 0),
    (1, 4, 2),  # AUTO.TAKEOFF while flying
])
def test_do_set_mode_rejections(p1: float, p2: float, p3: float) -> None:
    r = Rig()
    assert r.cmd(176, p1, p2, p3) == TEMPORARILY_REJECTED
    assert r.px4.mode is Mode.POSCTL


_floats = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0.0, 1.0, 6.0, 4.0, 3.0, 21196.0]))
_events = st.lists(st.one_of(
    st.tuples(st.just("cmd"), st.sampled_from([20, 21, 22, 176, 185, 400, 0, 65535]),
              st.tuples(*[_floats] * 7)),
    st.tuples(st.just("sp"), st.integers(0, 255), st.tuples(*[_floats] * 8)),
    st.tuples(st.just("wait"), st.floats(0.0, 3.0), st.just(()))), max_size=25)


@settings(max_examples=100, deadline=None)
@given(events=_events, airborne=st.booleans())
def test_any_input_sequence_keeps_the_state_machine_sane(events: list, airborne: bool) -> None:
    r = Rig(airborne=airborne)
    for kind, a, b in events:
        if kind == "cmd":
            assert r.cmd(a, *b) in (ACCEPTED, TEMPORARILY_REJECTED, 2, UNSUPPORTED)
        elif kind == "sp":
            r.px4.on_attitude_target(r.t, AttitudeTarget(a, b[:4], b[4:7], b[7]))
        else:
            r.run(round(a / DT) * DT)
        cmd = r.px4.attitude_command()
        vals = (cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad, cmd.thrust_norm)
        assert all(math.isfinite(v) for v in vals), (kind, vals)
        assert np.all(np.isfinite(r.s.pos_ned_m)) and r.s.pos_ned_m[2] <= 0.3
        assert (r.px4.mode.custom_mode >> 16) & 0xFF in (1, 2, 3, 4, 5, 6, 7)
