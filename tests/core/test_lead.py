"""Tilt-lag lead (companion/core/lead.py): the command that makes a lagged vehicle fly the
acceleration the controller planned, bounded, restarted after gaps; and in the pipeline, led
only while our setpoints fly the vehicle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion import ConfigError
from companion.config import load_config
from companion.control.pipeline import ControlPipeline, StepResult
from companion.control.wiring import new_store
from companion.core.errors import ParamError
from companion.core.lead import LeadParams, TiltLead
from companion.core.rmpc import RmpcResult, TargetMotion
from tests.companion.test_latency_preflight import _NoImages, _target_seen, _telemetry

DT_CTRL = 0.05


def _fly_lagged(tau: float, lead_s: float, t_end: float = 6.0) -> float:
    """RMS (m/s^2) between the planned horizontal acceleration (a 0.4 Hz sine of 1 m/s^2,
    sampled at 20 Hz) and what a first-order lag ``tau`` realises from the commands (zero-order
    hold, 1 ms integration), after the first second."""
    lead = TiltLead(LeadParams(attitude_lag_s=lead_s, max_m_s2=10.0))
    a = np.zeros(2)
    cmd = np.zeros(2)
    err = []
    h = 0.001
    n_ctrl = round(DT_CTRL / h)
    for i in range(round(t_end / h)):
        t = i * h
        if i % n_ctrl == 0:
            w = 2 * math.pi * 0.4 * t
            want = np.array([math.sin(w), 0.5 * math.cos(w)])
            cmd, _ = lead.apply(t, want) if lead_s > 0 else (want, None)
        a = a + h / tau * (cmd - a)
        if t >= 1.0:
            t_next = t + h
            want_now = np.array([math.sin(2 * math.pi * 0.4 * t_next),
                                 0.5 * math.cos(2 * math.pi * 0.4 * t_next)])
            err.append(float(np.sum((a - want_now) ** 2)))
    return math.sqrt(float(np.mean(err)))


@pytest.mark.parametrize("tau", [0.1, 0.2])
def test_lead_makes_a_lagged_vehicle_fly_the_planned_acceleration(tau: float) -> None:
    plain = _fly_lagged(tau, 0.0)
    led = _fly_lagged(tau, tau)
    # the lag alone is a phase shift of ~atan(2 pi 0.4 tau): 0.25-0.47 rad of a 1 m/s^2 sine
    assert plain > 0.15
    # the matched lead leaves the zero-order hold's half-step delay (~0.06 rad) only
    assert led < 0.35 * plain, (plain, led)
    # a lead twice too long overshoots: worse than matched (the constant matters)
    assert _fly_lagged(tau, 2.0 * tau) > led


def test_lead_term_is_the_lagged_derivative_and_bounded() -> None:
    lead = TiltLead(LeadParams(attitude_lag_s=0.1, max_m_s2=1.5))
    c, term = lead.apply(0.0, [0.0, 0.0])
    assert np.all(term == 0.0) and np.all(c == 0.0)  # nothing to difference yet
    c, term = lead.apply(0.05, [0.2, -0.1])
    np.testing.assert_allclose(term, 0.1 * np.array([0.2, -0.1]) / 0.05)
    np.testing.assert_allclose(c, np.array([0.2, -0.1]) + term)
    _, term = lead.apply(0.10, [5.2, -0.1])  # a jump: the kick is bounded in norm
    assert math.isclose(float(np.linalg.norm(term)), 1.5)
    assert term[0] > 0 and abs(term[1]) < 1e-12


def test_lead_restarts_after_a_gap_a_reset_and_bad_input() -> None:
    lead = TiltLead(LeadParams(attitude_lag_s=0.1, max_gap_s=0.15))
    lead.apply(0.0, [0.0, 0.0])
    _, term = lead.apply(0.5, [1.0, 0.0])  # 0.5 s later: no derivative across the gap
    assert np.all(term == 0.0)
    lead.reset()
    _, term = lead.apply(0.55, [0.0, 1.0])
    assert np.all(term == 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        lead.apply(0.6, [math.nan, 0.0])
    _, term = lead.apply(0.65, [3.0, 3.0])  # the bad sample restarted it
    assert np.all(term == 0.0)
    off = TiltLead(LeadParams(enabled=False))
    off.apply(0.0, [0.0, 0.0])
    c, term = off.apply(0.05, [1.0, 1.0])
    assert np.all(term == 0.0) and np.allclose(c, [1.0, 1.0])


@pytest.mark.parametrize("bad", [{"attitude_lag_s": -0.1}, {"attitude_lag_s": math.nan},
                                 {"attitude_lag_s": 2.0}, {"max_m_s2": -1.0},
                                 {"max_gap_s": 0.0}])
def test_lead_params_are_checked(bad: dict[str, float]) -> None:
    with pytest.raises(ParamError, match=r"control\.lead"):
        LeadParams(**bad)


def test_config_refuses_a_bad_lead_key() -> None:
    with pytest.raises(ConfigError, match=r"control\.lead\.attitude_lag_s"):
        load_config(overrides=["control.lead.attitude_lag_s=-1"])


class _RampSolver:
    """``mode`` ('optimal' or 'recovery') with an input that grows by 0.1 m/s^2 north per call
    (a planned ramp)."""

    def __init__(self, horizon: int, mode: str = "optimal") -> None:
        self.n = horizon
        self.k = 0
        self.mode = mode

    def solve(self, eta0: np.ndarray, motion: TargetMotion) -> RmpcResult:
        self.k += 1
        u = np.array([0.1 * self.k, 0.0, 0.0, 0.0])
        return RmpcResult(True, self.mode, "ok", "ok", 0.0, 1, 0.0, u,
                          np.tile(eta0, (self.n + 1, 1)), np.tile(u, (self.n, 1)), 0.0,
                          (), motion)


def _steps(in_control: bool, lag_s: float, n: int = 6,
           mode: str = "optimal") -> list[StepResult]:
    cfg = load_config(overrides=[f"control.lead.attitude_lag_s={lag_s}",
                                 "control.estimator.enabled=false",
                                 "control.latency.enabled=false"])
    pipe = ControlPipeline(cfg, _NoImages(), rmpc=_RampSolver(cfg.rmpc.horizon, mode))  # type: ignore[arg-type]
    store = new_store(cfg)
    seen = _target_seen(cfg.rmpc.desired_depth_m, cfg.camera.focal_length_m,
                        cfg.target.length_m, cfg.target.width_m)
    out = []
    t = 0.0
    for _ in range(n):
        t += 0.05
        _telemetry(store, t, offboard=in_control)
        out.append(pipe.step(None, t, store, t_now_s=t, in_control=in_control, perceived=seen))
    return out


def test_pipeline_leads_only_while_in_control() -> None:
    flown = _steps(True, 0.1)
    plain = _steps(True, 0.0)
    streamed = _steps(False, 0.1)
    for a, b in zip(flown[1:], plain[1:], strict=True):
        assert a.lead_m_s2 is not None and a.setpoint is not None and b.setpoint is not None
        # yaw 0: north = virtual x; the ramp's slope 0.1 / 0.05 s times 0.1 s = 0.2 m/s^2
        np.testing.assert_allclose(a.lead_m_s2, [0.2, 0.0], atol=1e-9)
        # a north acceleration is a nose-down pitch: the led command pitches further
        assert a.setpoint.pitch_rad < b.setpoint.pitch_rad
        # the controller's input (what the latency prediction integrates) is not led
        np.testing.assert_allclose(a.u, b.u)
    for r in streamed:
        assert r.lead_m_s2 is None
    for a, b in zip(streamed, plain, strict=True):
        assert a.setpoint is not None and b.setpoint is not None
        assert math.isclose(a.setpoint.pitch_rad, b.setpoint.pitch_rad, abs_tol=1e-12)
    assert flown[1].to_record()["lead_m_s2"] == pytest.approx([0.2, 0.0])


@pytest.mark.parametrize("mode", ["recovery", "fallback"])
def test_pipeline_does_not_lead_the_recovery_or_a_fallback(mode: str) -> None:
    """The soft problem's chase and the terminal law are flown as commanded: no lead term,
    the plain setpoint."""
    rec = _steps(True, 0.1, mode=mode)
    plain = _steps(True, 0.0, mode=mode)
    for a, b in zip(rec, plain, strict=True):
        assert a.rmpc is not None and a.rmpc.mode == mode
        assert a.lead_m_s2 is None and a.setpoint is not None and b.setpoint is not None
        assert math.isclose(a.setpoint.pitch_rad, b.setpoint.pitch_rad, abs_tol=1e-12)
