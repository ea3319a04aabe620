"""The estimator with the accelerometer (companion/core/disturbance.py ``update_accel``)
against a simulated vehicle: PX4's thrust mapping ``a = g e_z - g T / h R e_z + d`` integrated
finely, velocity samples at 30 Hz, HIGHRES_IMU at 50 Hz reading the true specific force in body
axes (``R' (a - g e_z)``) plus a constant bias and white noise. The accelerometer must make the
estimate follow a changing disturbance sooner, and a biased accelerometer must not move the
steady estimate (the velocity pins it; the bias state takes the offset)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.disturbance import DisturbanceEstimator, EstimatorParams, compensated_input
from companion.core.geometry import rotation_from_quat
from companion.core.setpoint import attitude_setpoint

G = 9.81
H_TRUE = 0.55
DT = 0.0025  # integration step; 30 Hz velocity = every 13th, 50 Hz accelerometer = every 8th


def fly(params: EstimatorParams, d_of_t, duration_s: float, *, bias=(0.0, 0.0),
        accel_noise: float = 0.0, vel_noise: float = 0.0, seed: int = 0,
        use_accel: bool = True) -> tuple[DisturbanceEstimator, list[tuple[float, np.ndarray,
                                                                        np.ndarray]]]:
    """Hover (u = 0 with the estimate's compensation, 20 Hz commands, slowly yawing); returns
    the filter and ``(t, d_true, d_hat)`` at every command."""
    rng = np.random.default_rng(seed)
    est = DisturbanceEstimator(params, 0.5)
    v = np.zeros(3)
    sp = None
    trace = []
    for i in range(round(duration_s / DT)):
        t = i * DT
        d = np.asarray(d_of_t(t), dtype=float)
        if i % 20 == 0:
            e = est.estimate()
            yaw = 0.3 * t
            sp = attitude_setpoint(compensated_input(np.zeros(4), e.d_ned_m_s2, yaw), yaw, 0.0,
                                   hover_thrust=e.hover_thrust, thrust_min=0.05,
                                   thrust_max=0.95)
            trace.append((t, d, np.array(e.d_ned_m_s2)))
        assert sp is not None
        rot = rotation_from_quat(sp.q_wxyz)
        b = rot[:, 2]
        a = np.array([0.0, 0.0, G]) - G * sp.thrust_norm / H_TRUE * b + d
        v = v + a * DT
        if i % 13 == 0 and i > 0:
            est.update(t, v + rng.normal(0.0, vel_noise, 3), sp.thrust_norm, b)
        elif use_accel and i % 8 == 0 and i > 0:
            f_body = rot.T @ (a - np.array([0.0, 0.0, G]))
            meas = f_body[:2] + np.asarray(bias) + rng.normal(0.0, accel_noise, 2)
            est.update_accel(t, meas, sp.thrust_norm, b, rot)
    return est, trace


# a quiet accelerometer (0.02 m/s^2 per sample) and a velocity with 0.01 m/s of noise: the
# estimator's behaviour, not the realistic world's figures (docs/reference/estimator.md, 1b)
ACCEL = EstimatorParams(accelerometer=True, accel_noise_m_s2=0.02,
                        accel_bias_noise_m_s2_sqrt_s=0.002)
VEL_NOISE = 0.01


def _rms(trace, t0: float, t1: float = math.inf) -> float:
    err = [np.linalg.norm((dh - d)[:2]) for t, d, dh in trace if t0 <= t < t1]
    return float(np.sqrt(np.mean(np.square(err))))


def test_the_accelerometer_follows_a_step_sooner() -> None:
    """A 0.4 m/s^2 gust from t = 10 s: over the second after it, the estimate's RMS error is
    at most 70 % of the velocity-only filter's (a biased accelerometer, its bias learnt
    before the gust). The very first command after the step cannot know it in either case."""
    def step(t: float) -> np.ndarray:
        return np.array([0.1, -0.05, 0.0]) + (np.array([0.3, -0.25, 0.0]) if t >= 10 else 0)

    _, with_acc = fly(ACCEL, step, 11.0, bias=(0.1, -0.08), accel_noise=0.02,
                      vel_noise=VEL_NOISE)
    _, without = fly(EstimatorParams(), step, 11.0, vel_noise=VEL_NOISE)
    assert _rms(with_acc, 10.0, 11.0) < 0.7 * _rms(without, 10.0, 11.0), (
        _rms(with_acc, 10.0, 11.0), _rms(without, 10.0, 11.0))


def test_the_accelerometer_follows_a_sinusoid_closer() -> None:
    """A 0.3 Hz, 0.2 m/s^2 rotating disturbance: the estimate's RMS error over the last 10 s
    is less than half of the velocity-only filter's."""
    def sine(t: float) -> np.ndarray:
        return 0.2 * np.array([math.sin(2 * math.pi * 0.3 * t), math.cos(2 * math.pi * 0.3 * t),
                               0.0])

    _, with_acc = fly(ACCEL, sine, 20.0, bias=(-0.1, 0.12), accel_noise=0.02,
                      vel_noise=VEL_NOISE)
    _, without = fly(EstimatorParams(), sine, 20.0, vel_noise=VEL_NOISE)
    assert _rms(with_acc, 10.0) < 0.5 * _rms(without, 10.0), (_rms(with_acc, 10.0),
                                                              _rms(without, 10.0))


@pytest.mark.parametrize("bias", [(0.3, -0.2), (-0.25, 0.0)])
def test_a_biased_accelerometer_does_not_move_the_steady_estimate(bias) -> None:
    """A steady wind and an accelerometer biased by up to 0.3 m/s^2 (six times the wind's
    error budget): after 30 s the estimate is the true wind (the velocity pins it) and the
    filter's bias state holds the accelerometer's bias."""
    d = np.array([0.4, -0.3, 0.0])
    est, _ = fly(ACCEL, lambda t: d, 30.0, bias=bias, accel_noise=0.02, vel_noise=VEL_NOISE,
                 seed=3)
    e = est.estimate()
    assert np.allclose(e.d_ned_m_s2[:2], d[:2], atol=0.02), e.d_ned_m_s2
    assert e.accel_bias_m_s2 is not None
    assert np.allclose(e.accel_bias_m_s2, bias, atol=0.03), e.accel_bias_m_s2
    assert e.hover_thrust == pytest.approx(H_TRUE, abs=0.005)
    assert e.accel_updates > 1000 and e.rejected == 0


def test_without_the_accelerometer_the_filter_is_the_velocity_filter() -> None:
    """``accelerometer = false``: samples are ignored, the state has 7 entries, and the
    estimate is exactly the velocity-only filter's."""
    def wind(t: float) -> np.ndarray:
        return np.array([0.3, 0.1, 0.0])

    est_a, tr_a = fly(EstimatorParams(), wind, 3.0, bias=(0.5, 0.5), use_accel=True)
    est_b, tr_b = fly(EstimatorParams(), wind, 3.0, use_accel=False)
    assert est_a.x.shape == (7,) and est_a.accel_updates == 0
    assert all(np.array_equal(a[2], b[2]) for a, b in zip(tr_a, tr_b, strict=True))
    assert est_a.estimate().to_record() == est_b.estimate().to_record()
    assert "accel_bias_m_s2" not in est_a.estimate().to_record()


def _running() -> DisturbanceEstimator:
    est, _ = fly(ACCEL, lambda t: np.array([0.2, 0.0, 0.0]), 2.0, accel_noise=0.02)
    return est


@pytest.mark.parametrize("f_xy", [(math.nan, 0.0), (0.0, math.inf), (45.0, 0.0), (1.0,)])
def test_bad_accelerometer_samples_are_rejected_and_change_nothing(f_xy) -> None:
    est = _running()
    x, p, n = est.x.copy(), est.p.copy(), est.rejected
    t = float(est.t_s) + 0.02
    assert not est.update_accel(t, f_xy, 0.55, [0.0, 0.0, 1.0], np.eye(3))
    assert est.rejected == n + 1 and est.reason
    assert np.array_equal(est.x, x) and np.array_equal(est.p, p)


def test_stale_or_unusable_samples_are_no_update() -> None:
    """Older than the filter, no known thrust, a stale velocity, a filter not yet running, a
    non-rotation attitude: not used, the estimate untouched."""
    est = _running()
    x, t0 = est.x.copy(), float(est.t_s)
    assert not est.update_accel(t0 - 0.01, (0.1, 0.0), 0.55, [0.0, 0.0, 1.0], np.eye(3))
    assert not est.update_accel(t0 + 0.02, (0.1, 0.0), None, None, np.eye(3))
    assert not est.update_accel(t0 + 0.9, (0.1, 0.0), 0.55, [0.0, 0.0, 1.0], np.eye(3))
    assert not est.update_accel(t0 + 0.02, (0.1, 0.0), 0.55, [0.0, 0.0, 1.0], 2 * np.eye(3))
    assert np.array_equal(est.x, x)
    fresh = DisturbanceEstimator(ACCEL, 0.5)
    assert not fresh.update_accel(1.0, (0.1, 0.0), 0.5, [0.0, 0.0, 1.0], np.eye(3))
    assert fresh.accel_updates == 0


def test_accelerometer_keys_are_validated() -> None:
    from companion.core.errors import ParamError
    for key in ("accel_noise_m_s2", "accel_bias_initial_std_m_s2", "accel_max_m_s2"):
        with pytest.raises(ParamError, match=key):
            EstimatorParams(**{key: 0.0})
    with pytest.raises(ParamError, match="accel_bias_noise_m_s2_sqrt_s"):
        EstimatorParams(accel_bias_noise_m_s2_sqrt_s=-1.0)
