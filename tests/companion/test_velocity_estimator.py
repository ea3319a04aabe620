"""The target-velocity estimator used when FOLLOW_TARGET is stale (spec 4 inverted)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.dynamics import euler_step
from companion.core.estimator import ImageVelocityEstimator

Z_STAR = 2.0


@pytest.mark.parametrize("yaw_rate", [0.0, 0.2])
def test_estimator_recovers_the_target_velocity(yaw_rate: float) -> None:
    """Fly the error dynamics with a known target velocity and vehicle motion; the estimator,
    seeing only s, the vehicle's own velocity and yaw, must recover the target's NED velocity."""
    dt = 0.05
    v_a_ned = np.array([0.3, -0.2, 0.0])
    v_q_v = np.array([0.1, 0.05, 0.0])  # vehicle velocity in the virtual frame (held)
    yaw = 0.4
    est = ImageVelocityEstimator(Z_STAR, alpha=0.2)
    # |s1|, |s2| ~ 0.2: a wrong sign in the yaw-rate terms would be off by ~0.2 m/s
    eta = np.array([0.2, -0.25, 0.0, 0.1, 0.0, 0.0, 0.0])
    for k in range(200):
        c, s = math.cos(yaw), math.sin(yaw)
        v_a_v = np.array([c * v_a_ned[0] + s * v_a_ned[1], -s * v_a_ned[0] + c * v_a_ned[1]])
        eta[4:6] = v_q_v[:2] - v_a_v
        s_feat = eta[:4] + np.array([0.0, 0.0, 1.0, 0.0])
        out = est.update(k * dt, s_feat, v_q_v, yaw, yaw_rate)
        # the target's velocity seen from the turning frame changes: vdot as spec 4 says
        vdot = yaw_rate * np.array([v_a_v[1], -v_a_v[0]])
        u = np.array([0.0, 0.0, 0.0, yaw_rate])
        eta = euler_step(eta, u, v_a_v, vdot, 0.0, Z_STAR, dt)
        yaw += yaw_rate * dt
    np.testing.assert_allclose(out[:2], v_a_ned[:2], atol=0.02)
