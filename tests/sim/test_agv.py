"""AGV trajectories: analytic derivatives against finite differences, the paper's path values
(spec section 8), speed scaling, and the heading while stopped."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim_bridge import ConfigError
from sim_bridge.physics.agv import KINDS, AgvTrajectory

H = 1e-4  # central-difference step (s)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=60, deadline=None)
@given(t=st.floats(0.0, 300.0), scale=st.sampled_from([0.5, 1.0, 2.5]))
def test_derivatives_match_finite_differences(kind: str, t: float, scale: float) -> None:
    traj = AgvTrajectory(kind, speed_scale=scale, top_z_m=-0.7)
    s, a, b = traj.state(t), traj.state(t + H), traj.state(t - H)
    if kind == "stop_and_go":  # the acceleration has corners at phase changes: avoid them
        tau = (scale * t) % 12.0
        if min(abs(tau), abs(tau - 8.0), abs(tau - 12.0)) < 4 * H * scale:
            return
    if kind == "ramp" and min(t, abs(t - 0.3 * scale)) < 4 * H:  # start and end of the ramp
        return
    np.testing.assert_allclose((a.pos_ned_m - b.pos_ned_m) / (2 * H), s.vel_ned_m_s, atol=1e-7)
    np.testing.assert_allclose((a.vel_ned_m_s - b.vel_ned_m_s) / (2 * H), s.acc_ned_m_s2, atol=1e-7)
    dyaw = _wrap(a.yaw_rad - b.yaw_rad) / (2 * H)
    assert dyaw == pytest.approx(s.yaw_rate_rad_s, abs=1e-6)
    assert s.pos_ned_m[2] == -0.7 and s.vel_ned_m_s[2] == 0.0 and s.acc_ned_m_s2[2] == 0.0
    speed = float(np.hypot(*s.vel_ned_m_s[:2]))
    if speed > 1e-9:  # the heading is the direction of travel
        assert _wrap(s.yaw_rad - math.atan2(s.vel_ned_m_s[1], s.vel_ned_m_s[0])) == pytest.approx(
            0.0, abs=1e-9
        )


def test_paper_path_values() -> None:
    traj = AgvTrajectory("paper")
    s0 = traj.state(0.0)
    np.testing.assert_allclose(s0.pos_ned_m, [0.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(s0.vel_ned_m_s, [0.1, 0.1, 0.0], atol=1e-15)
    assert s0.yaw_rad == pytest.approx(math.pi / 4, abs=1e-15)
    assert s0.yaw_rate_rad_s == pytest.approx(0.0, abs=1e-15)
    s = traj.state(100.0)
    xd, yd = 0.1, 0.1 * math.cos(2.5)
    ydd = -4 * 0.025**2 * math.sin(2.5)
    np.testing.assert_allclose(s.pos_ned_m, [10.0, 4 * math.sin(2.5), 0.0], atol=1e-12)
    np.testing.assert_allclose(s.vel_ned_m_s, [xd, yd, 0.0], atol=1e-15)
    np.testing.assert_allclose(s.acc_ned_m_s2, [0.0, ydd, 0.0], atol=1e-15)
    assert s.yaw_rad == pytest.approx(math.atan2(yd, xd), abs=1e-15)
    assert s.yaw_rate_rad_s == pytest.approx(xd * ydd / (xd**2 + yd**2), rel=1e-12)
    # one period of the lateral sine: 2 pi / 0.025 s
    p = traj.state(2 * math.pi / 0.025)
    np.testing.assert_allclose(p.pos_ned_m[:2], [0.1 * 2 * math.pi / 0.025, 0.0], atol=1e-9)


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "ramp"])
def test_every_kind_starts_at_origin_and_speed_scale_rescales_time(kind: str) -> None:
    base = AgvTrajectory(kind, top_z_m=0.25)
    fast = AgvTrajectory(kind, speed_scale=2.0, top_z_m=0.25)
    np.testing.assert_allclose(base.state(0.0).pos_ned_m, [0.0, 0.0, 0.25], atol=1e-15)
    for t in (0.0, 3.3, 41.0, 97.5):
        a, b = base.state(2.0 * t), fast.state(t)
        np.testing.assert_allclose(b.pos_ned_m, a.pos_ned_m, atol=1e-12)
        np.testing.assert_allclose(b.vel_ned_m_s, 2.0 * a.vel_ned_m_s, atol=1e-12)
        np.testing.assert_allclose(b.acc_ned_m_s2, 4.0 * a.acc_ned_m_s2, atol=1e-12)
        assert b.yaw_rad == pytest.approx(a.yaw_rad, abs=1e-12)
        assert b.yaw_rate_rad_s == pytest.approx(2.0 * a.yaw_rate_rad_s, abs=1e-12)


def test_stop_and_go_stops_smoothly_and_keeps_its_heading() -> None:
    traj = AgvTrajectory("stop_and_go")
    ts = np.arange(0.0, 60.0, 0.01)
    states = [traj.state(t) for t in ts]
    speed = np.array([np.hypot(*s.vel_ned_m_s[:2]) for s in states])
    acc = np.array([np.linalg.norm(s.acc_ned_m_s2) for s in states])
    stopped = speed < 1e-12
    assert stopped.any() and (~stopped).any()
    assert acc.max() < 0.5  # finite, bounded accelerations
    # speed and acceleration are continuous (no jumps between samples)
    assert np.abs(np.diff(speed)).max() < 0.01 * 0.5
    for i in np.nonzero(stopped)[0][1:]:
        if stopped[i - 1]:
            assert states[i].yaw_rad == states[i - 1].yaw_rad
            assert states[i].yaw_rate_rad_s == 0.0
            np.testing.assert_array_equal(states[i].pos_ned_m, states[i - 1].pos_ned_m)
    # it goes somewhere: one go phase moves 2 m along the path
    assert states[-1].pos_ned_m[0] > 8.0


@pytest.mark.parametrize(("scale", "accel"), [(10.0, 1.0), (5.0, 1.0), (10.0, 2.5)])
def test_ramp_accelerates_from_rest_to_its_cruise_speed(scale: float, accel: float) -> None:
    traj = AgvTrajectory("ramp", speed_scale=scale, top_z_m=0.1, ramp_accel_m_s2=accel)
    cruise = 0.3 * scale
    t_c = cruise / accel
    s0 = traj.state(0.0)
    np.testing.assert_allclose(s0.pos_ned_m, [0.0, 0.0, 0.1], atol=1e-15)
    np.testing.assert_allclose(s0.vel_ned_m_s, 0.0, atol=1e-15)
    np.testing.assert_allclose(s0.acc_ned_m_s2, [accel, 0.0, 0.0], atol=1e-15)
    mid = traj.state(0.5 * t_c)
    assert mid.vel_ned_m_s[0] == pytest.approx(0.5 * cruise) and mid.acc_ned_m_s2[0] == accel
    end = traj.state(t_c + 2.0)
    np.testing.assert_allclose(end.vel_ned_m_s, [cruise, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(end.acc_ned_m_s2, 0.0, atol=1e-15)
    # distance: the ramp's cruise * t_c / 2, then cruise * 2 s; heading north all along
    assert end.pos_ned_m[0] == pytest.approx(0.5 * cruise * t_c + 2.0 * cruise, rel=1e-12)
    assert end.pos_ned_m[1] == 0.0 and end.yaw_rad == 0.0 and end.yaw_rate_rad_s == 0.0
    # the position is continuous through the end of the ramp
    a, b = traj.state(t_c - 1e-9), traj.state(t_c + 1e-9)
    np.testing.assert_allclose(a.pos_ned_m, b.pos_ned_m, atol=1e-8)
    np.testing.assert_allclose(a.vel_ned_m_s, b.vel_ned_m_s, atol=1e-8)


def test_bad_arguments_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"sim\.agv\.trajectory"):
        AgvTrajectory("spiral")
    with pytest.raises(ConfigError, match=r"sim\.agv\.speed_scale"):
        AgvTrajectory("paper", speed_scale=0.0)
    with pytest.raises(ConfigError, match=r"sim\.agv\.ramp_accel_m_s2"):
        AgvTrajectory("ramp", ramp_accel_m_s2=0.0)
    with pytest.raises(ConfigError, match=r"pos_ned_m"):
        from sim_bridge.physics.agv import AgvState

        AgvState(0.0, [0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, 0.0)
