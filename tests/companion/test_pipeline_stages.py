"""Each stage of ``ControlPipeline.step`` called alone, on its typed inputs (issue 25).

perceive -> state_at_frame -> predict -> plan -> decide -> command: every stage is checked
against an oracle computed without the pipeline (the core function it must wire, the safety
rule, the level hover), and the step is checked to be exactly the stages in sequence.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import load_config
from companion.control.pipeline import ControlPipeline
from companion.control.safety import SafetyDecision, SafetyLevel
from companion.control.stages import FrameState, Plan, Predicted, Sighting
from companion.control.telemetry import TelemetryStore
from companion.control.wiring import new_store
from companion.core.geometry import rectangle_corners_m
from companion.core.latency import predict_error_state
from companion.core.rmpc import RmpcResult, TargetMotion
from companion.core.setpoint import hover_setpoint
from companion.core.state import build_error_state
from companion.perception.pipeline import PerceptionResult

AUTOPILOT = 1
PX4_OFFBOARD = 6 << 16
U_ASKED = np.array([0.4, -0.3, 0.2, 0.05])


class _ConstantSolver:
    """'optimal' with a fixed input: isolates the stages from the solver."""

    def __init__(self, horizon: int) -> None:
        self.n = horizon
        self.calls = 0

    def solve(self, eta0: np.ndarray, motion: TargetMotion) -> RmpcResult:
        self.calls += 1
        return RmpcResult(True, "optimal", "ok", "ok", 0.0, 1, 0.0, U_ASKED.copy(),
                          np.tile(eta0, (self.n + 1, 1)), np.tile(U_ASKED, (self.n, 1)), 0.0,
                          (), motion)

    def reset(self) -> None:
        pass


class _NoImages:
    def process(self, image: object) -> PerceptionResult:  # pragma: no cover - never called
        raise AssertionError("perception is given")


def _pipeline(*overrides: str) -> tuple[ControlPipeline, _ConstantSolver]:
    cfg = load_config(None, list(overrides))
    solver = _ConstantSolver(cfg.rmpc.horizon)
    return ControlPipeline(cfg, _NoImages(), rmpc=solver), solver  # type: ignore[arg-type]


def _seen(pipe: ControlPipeline) -> PerceptionResult:
    """The target 0.3 m off the optical axis, seen by a level camera at the desired depth."""
    cfg = pipe.cfg
    pts = rectangle_corners_m(cfg.target.length_m, cfg.target.width_m) + np.array([0.3, -0.2])
    points_m = cfg.camera.focal_length_m * pts / cfg.rmpc.desired_depth_m
    return PerceptionResult("ok", "", np.ones((4, 2)), np.zeros((4, 2)), points_m, 1.0)


def _telemetry(store: TelemetryStore, t: float, yaw_rad: float = 0.3) -> None:
    store.ingest("HEARTBEAT", {"custom_mode": PX4_OFFBOARD, "base_mode": 128 | 1}, t, AUTOPILOT)
    h = 0.5 * yaw_rad
    store.ingest("ATTITUDE_QUATERNION", {"q1": math.cos(h), "q2": 0.0, "q3": 0.0,
                                         "q4": math.sin(h), "yawspeed": 0.0}, t, AUTOPILOT)
    store.ingest("LOCAL_POSITION_NED", {"x": 0.0, "y": 0.0, "z": -2.0, "vx": 0.1, "vy": 0.0,
                                        "vz": 0.0}, t, AUTOPILOT)


def _store(pipe: ControlPipeline, t: float) -> TelemetryStore:
    store = new_store(pipe.cfg)
    for k in range(3):
        _telemetry(store, t - 0.05 + k / 60.0)
    return store


def test_perceive_passes_corners_only_for_a_target_seen() -> None:
    pipe, _ = _pipeline()
    seen = pipe.perceive(None, _seen(pipe))
    assert seen.status == "ok" and seen.points_m is not None and seen.corners_px is not None
    assert pipe.perceive(None, None) == Sighting("lost", "no image")
    lost = pipe.perceive(None, PerceptionResult("lost", "no blob", np.ones((4, 2)),
                                                np.zeros((4, 2)), np.zeros((4, 2)), 0.0))
    assert lost.status == "lost" and lost.points_m is None and lost.corners_px is None


def test_state_at_frame_builds_the_core_error_state() -> None:
    pipe, _ = _pipeline()
    t = 1.0
    store = _store(pipe, t)
    seen = pipe.perceive(None, _seen(pipe))
    state = pipe.state_at_frame(seen, t, store, in_control=True, t_now=t)
    assert state.error_state is not None and state.yaw_rad == pytest.approx(0.3)
    assert state.velocity is not None and state.inputs_finite
    cfg = pipe.cfg
    att = store.attitude_at(t)
    assert att is not None
    oracle = build_error_state(
        seen.points_m, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.3,  # type: ignore[arg-type]
        yaw_rate_rad_s=0.0, v_q_ned_m_s=np.array([0.1, 0.0, 0.0]),
        v_a_ned_m_s=state.velocity.v_a_ned_m_s, a_a_ned_m_s2=state.velocity.a_a_ned_m_s2,
        psidot_a_rad_s=state.velocity.yaw_rate_rad_s, a_star=pipe.a_star,
        lam=cfg.camera.focal_length_m, s4_prev_rad=None)
    np.testing.assert_allclose(state.error_state.eta_e, oracle.eta_e, atol=1e-9)


def test_state_at_frame_without_attitude_or_with_bad_points() -> None:
    pipe, _ = _pipeline()
    seen = pipe.perceive(None, _seen(pipe))
    bare = pipe.state_at_frame(seen, 1.0, new_store(pipe.cfg), in_control=None, t_now=1.0)
    assert bare.error_state is None and bare.yaw_rad is None and bare.inputs_finite
    bad = Sighting("ok", "", np.ones((4, 2)), np.full((4, 2), np.nan))
    rej = pipe.state_at_frame(bad, 1.0, _store(pipe, 1.0), in_control=True, t_now=1.0)
    assert rej.error_state is None and rej.perception_status == "rejected"
    # unusable target points are a degenerate target (the target is lost), not bad inputs
    assert rej.inputs_finite and "non-finite" in rej.perception_reason


def _state(pipe: ControlPipeline, t: float) -> tuple[FrameState, TelemetryStore]:
    store = _store(pipe, t)
    return pipe.state_at_frame(pipe.perceive(None, _seen(pipe)), t, store, True, t), store


def test_predict_moves_the_state_to_the_command_effect() -> None:
    pipe, _ = _pipeline()
    state, _ = _state(pipe, 1.0)
    assert state.error_state is not None
    pred = pipe.predict(state, 0.9, 1.0, 0.02)  # a frame 0.1 s old, 20 ms to act
    assert pred is not None and pred.prediction is not None
    v_a, vdot_a, psidot_a = pred.motion.stage(0)
    oracle = predict_error_state(state.error_state.eta_e, 0.9, 1.02, [], v_a, vdot_a,
                                 psidot_a, pipe.cfg.rmpc.desired_depth_m,
                                 pipe.cfg.control.latency)
    np.testing.assert_allclose(pred.eta0, oracle.eta_e, atol=1e-12)
    assert not np.allclose(pred.eta0, state.error_state.eta_e)  # it did move
    off, _ = _pipeline("control.latency.enabled=false")
    st_off, _ = _state(off, 1.0)
    p_off = off.predict(st_off, 0.9, 1.0, 0.02)
    assert p_off is not None and p_off.prediction is None
    assert st_off.error_state is not None
    np.testing.assert_array_equal(p_off.eta0, st_off.error_state.eta_e)
    assert pipe.predict(FrameState(None, None, None, None, None, True, "lost", ""),
                        1.0, 1.0, 0.0) is None


def test_plan_solves_or_falls_back() -> None:
    pipe, solver = _pipeline()
    state, _ = _state(pipe, 1.0)
    pred = pipe.predict(state, 1.0, 1.0, 0.0)
    assert isinstance(pred, Predicted)
    plan = pipe.plan(pred)
    assert plan.solver_ok and plan.result is not None and solver.calls == 1
    np.testing.assert_array_equal(plan.result.u0, U_ASKED)
    pipe.force_solver_failure = True
    failed = pipe.plan(pred)
    assert not failed.solver_ok and failed.result is not None
    assert failed.result.mode == "fallback" and solver.calls == 1  # the solver not asked
    assert pipe.plan(None) == Plan(None, True)


def test_decide_leaves_tracking_on_stale_telemetry() -> None:
    pipe, _ = _pipeline()
    state, store = _state(pipe, 1.0)
    plan = pipe.plan(pipe.predict(state, 1.0, 1.0, 0.0))
    assert pipe.decide(1.0, store, state, plan).level is SafetyLevel.TRACKING
    late = 1.0 + 10.0 * pipe.cfg.safety.telemetry_timeout_s
    assert pipe.decide(late, store, state, plan).level is not SafetyLevel.TRACKING


def test_command_flies_the_plan_or_holds() -> None:
    pipe, _ = _pipeline("control.estimator.enabled=false")
    state, store = _state(pipe, 1.0)
    pred = pipe.predict(state, 1.0, 1.0, 0.0)
    plan = pipe.plan(pred)
    tracking = SafetyDecision(SafetyLevel.TRACKING, "ok", False)
    cmd = pipe.command(tracking, state, pred, plan, store, False, 1.0, 1.0)
    assert cmd.setpoint is not None and cmd.u is not None and cmd.lead_m_s2 is None
    np.testing.assert_array_equal(cmd.u, U_ASKED)
    hover = pipe.command(SafetyDecision(SafetyLevel.HOVER, "x", True), state, pred, plan,
                         store, True, 1.05, 1.05)
    c = pipe.cfg.control
    level = hover_setpoint(0.3, hover_thrust=c.hover_thrust, thrust_min=c.thrust_min,
                           thrust_max=c.thrust_max)
    assert hover.u is None and hover.setpoint is not None
    np.testing.assert_allclose(hover.setpoint.q_wxyz, level.q_wxyz, atol=1e-12)
    assert hover.setpoint.thrust_norm == pytest.approx(level.thrust_norm)
    silent = pipe.command(SafetyDecision(SafetyLevel.SILENT, "x", True), state, pred, plan,
                          store, True, 1.1, 1.1)
    assert silent.setpoint is None and silent.u is None


def test_step_is_the_stages_in_sequence() -> None:
    """Two pipelines fed the same inputs, one by ``step``, one stage by stage: the same
    commands (the stages hold all the step does)."""
    a, _ = _pipeline()
    b, _ = _pipeline()
    for k in range(12):
        t = 0.05 * (k + 1)
        sa, sb = _store(a, t), _store(b, t)
        seen = _seen(a)
        res = a.step(None, t, sa, t_now_s=t, in_control=k > 3, perceived=seen)
        state = b.state_at_frame(b.perceive(None, seen), t, sb, k > 3, t)
        pred = b.predict(state, t, t, b.cfg.control.latency.actuation_delay_s)
        plan = b.plan(pred)
        decision = b.decide(t, sb, state, plan)
        cmd = b.command(decision, state, pred, plan, sb, k > 3,
                        t + b.cfg.control.latency.actuation_delay_s, t)
        assert res.setpoint is not None and cmd.setpoint is not None
        np.testing.assert_array_equal(res.setpoint.q_wxyz, cmd.setpoint.q_wxyz)
        assert res.setpoint.thrust_norm == cmd.setpoint.thrust_norm
        assert res.safety == decision
