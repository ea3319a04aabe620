"""Latency compensation integrates only the inputs the vehicle flew (issue 12).

Before OFFBOARD, PX4 streams our setpoints but flies its own position hold; the commands of the
pre-flight stream were never applied. The Smith-predictor step that moves an old frame's error
state to the moment the command takes effect must therefore integrate zero acceleration over
that stretch, not the RMPC inputs the companion sent. Checked on the real pipeline with a
solver stub that always asks for a large input: a pipeline that streamed while not in control
must predict with zero input, and one that was in control with the input it sent.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import load_config
from companion.control.pipeline import ControlPipeline, StepResult
from companion.control.telemetry import TelemetryStore
from companion.control.wiring import new_store
from companion.core.geometry import rectangle_corners_m
from companion.core.latency import predict_error_state
from companion.core.rmpc import RmpcResult, TargetMotion
from companion.perception.pipeline import PerceptionResult

AUTOPILOT = 1
PX4_OFFBOARD = 6 << 16
U_ASKED = np.array([1.2, -0.8, 0.5, 0.2])  # m/s^2 and rad/s: far from zero on purpose


class _ConstantSolver:
    """Always 'optimal' with the same large input (isolates the history, not the solver)."""

    def __init__(self, horizon: int) -> None:
        self.n = horizon

    def solve(self, eta0: np.ndarray, motion: TargetMotion) -> RmpcResult:
        return RmpcResult(True, "optimal", "ok", "ok", 0.0, 1, 0.0, U_ASKED.copy(),
                          np.tile(eta0, (self.n + 1, 1)), np.tile(U_ASKED, (self.n, 1)), 0.0,
                          (), motion)


class _NoImages:
    def process(self, image: object) -> None:  # pragma: no cover - frames come as `perceived`
        raise AssertionError("perception is given")


def _target_seen(cfg_depth: float, lam: float, length: float, width: float) -> PerceptionResult:
    """The target 0.3 m off the optical axis, seen by a level camera ``cfg_depth`` above it."""
    pts = rectangle_corners_m(length, width) + np.array([0.3, -0.2])
    points_m = lam * pts / cfg_depth
    return PerceptionResult("ok", "", np.zeros((4, 2)), np.zeros((4, 2)), points_m, 1.0)


def _telemetry(store: TelemetryStore, t: float, offboard: bool) -> None:
    mode = PX4_OFFBOARD if offboard else 3 << 16
    store.ingest("HEARTBEAT", {"custom_mode": mode, "base_mode": 128 | 1}, t, AUTOPILOT)
    store.ingest("ATTITUDE_QUATERNION", {"q1": 1.0, "q2": 0.0, "q3": 0.0, "q4": 0.0,
                                         "yawspeed": 0.0}, t, AUTOPILOT)
    store.ingest("LOCAL_POSITION_NED", {"x": 0.0, "y": 0.0, "z": -2.0, "vx": 0.1, "vy": 0.0,
                                        "vz": 0.0}, t, AUTOPILOT)


def _fly(preflight: bool) -> StepResult:
    """1 s of 20 Hz steps (``preflight``: the runtime's in-control flag over them), then the
    first in-control step on a frame captured 0.1 s before it runs."""
    cfg = load_config()
    pipe = ControlPipeline(cfg, _NoImages(), rmpc=_ConstantSolver(cfg.rmpc.horizon))  # type: ignore[arg-type]
    store = new_store(cfg)
    seen = _target_seen(cfg.rmpc.desired_depth_m, cfg.camera.focal_length_m,
                        cfg.target.length_m, cfg.target.width_m)
    t = 0.0
    for _ in range(20):
        t += 0.05
        for k in range(3):
            _telemetry(store, t - 0.05 + k / 60.0, offboard=False)
        res = pipe.step(None, t, store, t_now_s=t, in_control=preflight, perceived=seen)
        assert res.u is not None  # the stream carries the solver's input
    t += 0.05
    _telemetry(store, t, offboard=True)
    return pipe.step(None, t - 0.1, store, t_now_s=t, in_control=True, perceived=seen)


def _zero_input_prediction(r: StepResult) -> np.ndarray:
    """``r``'s frame predicted to its command time with nothing commanded (PX4's hold)."""
    cfg = load_config()
    assert r.error_state is not None and r.rmpc is not None and r.t_now_s is not None
    v_a, vdot_a, psidot_a = r.rmpc.target.stage(0)
    return predict_error_state(r.error_state.eta_e, r.t_s, r.t_now_s, [], v_a, vdot_a,
                               psidot_a, cfg.rmpc.desired_depth_m, cfg.control.latency).eta_e


def test_preflight_commands_are_not_integrated_by_the_latency_prediction() -> None:
    streamed = _fly(False)
    flown = _fly(True)
    for r in (streamed, flown):
        assert r.prediction is not None and math.isclose(r.prediction.horizon_s, 0.1)
    # PX4 held the vehicle over the frame's last 0.1 s: the prediction integrates zero input
    assert streamed.prediction is not None and flown.prediction is not None
    np.testing.assert_allclose(streamed.prediction.eta_e, _zero_input_prediction(streamed),
                               atol=1e-12)
    # ... whereas inputs that were flown move the predicted velocity error by ~U * 0.1 s
    dv = flown.prediction.eta_e - _zero_input_prediction(flown)
    assert np.max(np.abs(dv)) > 0.02
