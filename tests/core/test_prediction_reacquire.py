"""Horizon prediction of the target's motion and the reacquisition law."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.core.geometry import rot_z
from companion.core.prediction import predict_target_motion
from companion.core.reacquire import reacquire_input

U_MAX = (1.5, 1.5, 1.5, 0.3)


@settings(max_examples=60, deadline=None)
@given(
    speed=st.floats(0.05, 3.0), heading=st.floats(-np.pi, np.pi), w=st.floats(-0.5, 0.5),
    a_along=st.floats(-0.2, 0.2), yaw_q=st.floats(-np.pi, np.pi),
)
def test_vdot_is_the_rotating_frame_derivative_of_v(
    speed: float, heading: float, w: float, a_along: float, yaw_q: float
) -> None:
    t_hat = np.array([np.cos(heading), np.sin(heading), 0.0])
    n_hat = np.array([-np.sin(heading), np.cos(heading), 0.0])
    v = speed * t_hat
    a = a_along * t_hat + speed * w * n_hat  # consistent with a turn at rate w
    dt = 1e-3
    m = predict_target_motion(v, a, w, yaw_q, horizon=40, dt_s=dt)
    fd = np.diff(m.v_a_m_s, axis=0) / dt
    mid = 0.5 * (m.vdot_a_m_s2[1:] + m.vdot_a_m_s2[:-1])
    assert np.allclose(fd, mid, atol=1e-5)
    # stage 0 is the current velocity in the virtual frame
    assert np.allclose(m.v_a_m_s[0], (rot_z(yaw_q).T @ v)[:2], atol=1e-12)


def test_constant_target_velocity_seen_from_a_vehicle_turning_with_it() -> None:
    # target turning at w, vehicle yaw turning at w too: the velocity in v is constant
    m = predict_target_motion(np.array([1.0, 0, 0]), np.array([0, 0.3, 0]), 0.3, 0.0, 16, 0.05)
    assert np.allclose(m.v_a_m_s, m.v_a_m_s[0], atol=1e-12)
    assert np.allclose(m.vdot_a_m_s2, 0.0, atol=1e-12)


def test_reacquire_moves_towards_target_climbs_and_turns() -> None:
    u = reacquire_input(np.array([2.0, -1.0, 2.0]), np.zeros(3), np.zeros(3), np.zeros(3),
                        yaw_q_rad=0.0, yaw_a_rad=0.2, height_above_target_m=2.0,
                        climb_rate_m_s=0.3, max_height_m=4.0, u_max=U_MAX)
    assert u[0] > 0 and u[1] < 0      # towards the target (forward, left)
    assert u[2] < 0                   # climb: NED z down, so negative acceleration
    assert u[3] > 0                   # yaw towards its heading
    assert np.all(np.abs(u) <= np.array(U_MAX) + 1e-12)
    # at the height limit and hovering over a still target: no command
    u0 = reacquire_input(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.0, 0.0, 4.0,
                         0.3, 4.0, U_MAX)
    assert np.allclose(u0, 0.0)


def test_reacquire_refuses_non_finite() -> None:
    import pytest

    with pytest.raises(ValueError):
        reacquire_input(np.array([np.nan, 0, 0]), np.zeros(3), np.zeros(3), np.zeros(3),
                        0.0, 0.0, 2.0, 0.3, 4.0, U_MAX)


def test_speed_cap_holds_the_acceleration_only_up_to_the_bound() -> None:
    """``speed_cap_m_s``: the along-track acceleration is held until the predicted speed
    reaches max(now, cap), then the speed is held (and the predicted acceleration is zero);
    without a cap, or below it, the prediction is unchanged."""
    n, dt = 16, 0.05
    v, a = np.array([0.8, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    free = predict_target_motion(v, a, 0.0, 0.0, n, dt)
    capped = predict_target_motion(v, a, 0.0, 0.0, n, dt, speed_cap_m_s=1.0)
    sp = np.hypot(*capped.v_a_m_s.T)
    assert np.hypot(*free.v_a_m_s[-1]) == pytest.approx(0.8 + 15 * dt * 1.0)
    assert np.all(sp <= 1.0 + 1e-12) and sp[-1] == pytest.approx(1.0)
    reached = sp >= 1.0
    assert np.allclose(capped.vdot_a_m_s2[reached], 0.0)  # speed held: no acceleration
    assert np.allclose(capped.vdot_a_m_s2[~reached, 0], 1.0)  # accelerating before
    assert np.allclose(capped.v_a_m_s[~reached], free.v_a_m_s[~reached])
    # never below the measured speed: a target already faster keeps its speed
    fast = predict_target_motion(np.array([1.3, 0.0, 0.0]), a, 0.0, 0.0, n, dt,
                                 speed_cap_m_s=1.0)
    assert np.allclose(np.hypot(*fast.v_a_m_s.T), 1.3)
    # a cap the prediction never reaches, or a braking target: unchanged
    for vv, aa in ((np.array([0.2, 0.0, 0.0]), a), (v, -a)):
        assert np.allclose(predict_target_motion(vv, aa, 0.2, 0.1, n, dt,
                                                 speed_cap_m_s=1.0).v_a_m_s,
                           predict_target_motion(vv, aa, 0.2, 0.1, n, dt).v_a_m_s)


def test_advance_target_is_exact_on_a_constant_turn_and_a_ramp() -> None:
    """A FOLLOW_TARGET sample advanced by dt equals the target dt later: exact on a circle
    (constant speed and turn) and on a straight constant acceleration."""
    import math

    from companion.core.prediction import advance_target

    r, w = 3.0, 0.5  # 1.5 m/s on a 3 m circle

    def circle(t: float) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(w * t), math.sin(w * t)
        return (np.array([r * w * c, r * w * s, 0.0]),
                np.array([-r * w * w * s, r * w * w * c, 0.0]))

    for t, dt in ((0.0, 0.1), (2.0, -0.06), (7.3, 0.25)):
        v0, a0 = circle(t)
        v, a = advance_target(v0, a0, w, dt)
        ve, ae = circle(t + dt)
        np.testing.assert_allclose(v, ve, atol=1e-12)
        np.testing.assert_allclose(a, ae, atol=1e-12)
    v, a = advance_target(np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 0.0, 0.2)
    np.testing.assert_allclose(v, [1.2, 0.0, 0.0]) and np.testing.assert_allclose(a, [1, 0, 0])
    v, _ = advance_target(np.array([0.1, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), 0.0, 0.5)
    np.testing.assert_allclose(v, 0.0)  # braking to rest, not backwards
