"""Latency prediction (companion/core/latency.py) against the closed-form solution of the
error dynamics without rotation (psidot = 0: spec 4 is linear, se' = -ve/z*, ve' = u_e)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from companion.core.latency import LatencyParams, input_at, predict_error_state

Z = 2.0


def exact(eta0: np.ndarray, history: list[tuple[float, np.ndarray]], t0: float, t1: float,
          vdot_a: np.ndarray) -> np.ndarray:
    """Piecewise-constant acceleration, no yaw rate: integrate exactly segment by segment."""
    eta = eta0.copy()
    cuts = sorted({t0, t1, *[t for t, _ in history if t0 < t < t1]})
    for a, b in itertools.pairwise(cuts):
        h = b - a
        u = input_at(history, a)
        ue = np.array([u[0] - vdot_a[0], u[1] - vdot_a[1], u[2]])
        ve = eta[4:7]
        eta[0:3] = eta[0:3] - (ve * h + 0.5 * ue * h * h) / Z
        eta[4:7] = ve + ue * h
    return eta


def test_prediction_matches_the_exact_solution_across_input_changes() -> None:
    eta0 = np.array([0.05, -0.1, 0.2, 0.0, 0.3, -0.2, 0.1])
    hist = [(0.0, np.array([0.5, -0.2, 0.3, 0.0])), (0.03, np.array([-0.4, 0.6, -0.1, 0.0])),
            (0.07, np.array([1.0, 0.0, 0.5, 0.0]))]
    vdot_a = np.array([0.1, -0.05])
    p = predict_error_state(eta0, 0.01, 0.11, hist, [0.3, 0.1], vdot_a, 0.0, Z,
                            LatencyParams(step_s=0.001))
    want = exact(eta0, hist, 0.01, 0.11, vdot_a)
    # Euler with 1 ms steps: the position error is O(h) ue t ~ 1e-4 / z*
    assert np.allclose(p.eta_e, want, atol=2e-4)
    assert p.horizon_s == pytest.approx(0.1) and not p.clipped
    # and it is a real prediction: far from the measured state
    assert np.max(np.abs(p.eta_e - eta0)) > 0.02


def test_no_latency_changes_nothing_and_long_latency_is_clipped() -> None:
    eta0 = np.array([0.05, -0.1, 0.2, 0.1, 0.3, -0.2, 0.1])
    hist = [(0.0, np.array([0.5, -0.2, 0.3, 0.1]))]
    p0 = predict_error_state(eta0, 1.0, 1.0, hist, [0, 0], [0, 0], 0.0, Z, LatencyParams())
    assert np.array_equal(p0.eta_e, eta0) and p0.horizon_s == 0.0
    p1 = predict_error_state(eta0, 1.0, 0.9, hist, [0, 0], [0, 0], 0.0, Z, LatencyParams())
    assert np.array_equal(p1.eta_e, eta0)  # "now" before the capture: nothing to predict
    lp = LatencyParams(max_prediction_s=0.1)
    p2 = predict_error_state(eta0, 1.0, 2.0, hist, [0, 0], [0, 0], 0.0, Z, lp)
    p3 = predict_error_state(eta0, 1.0, 1.1, hist, [0, 0], [0, 0], 0.0, Z, lp)
    assert p2.clipped and p2.horizon_s == pytest.approx(0.1)
    assert np.allclose(p2.eta_e, p3.eta_e)


def test_yaw_rate_terms_are_integrated() -> None:
    """With a yaw rate the rotation terms act: s4 moves by -(psidot_q - psidot_a) t."""
    eta0 = np.array([0.1, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    hist = [(0.0, np.array([0.0, 0.0, 0.0, 0.5]))]
    p = predict_error_state(eta0, 0.0, 0.1, hist, [0, 0], [0, 0], 0.1, Z, LatencyParams())
    assert p.eta_e[3] == pytest.approx(0.2 - 0.4 * 0.1, abs=1e-9)
    assert p.eta_e[1] == pytest.approx(-0.1 * 0.5 * 0.1, rel=0.05)  # se2' = -s1 psidot


def test_input_before_any_command_is_zero() -> None:
    hist = [(1.0, np.ones(4))]
    assert np.array_equal(input_at(hist, 0.5), np.zeros(4))
    assert np.array_equal(input_at(hist, 1.0), np.ones(4))


def test_params_are_validated() -> None:
    from companion.core.errors import ParamError

    with pytest.raises(ParamError):
        LatencyParams(max_prediction_s=0.0)
    with pytest.raises(ParamError):
        LatencyParams(step_s=1.0)
