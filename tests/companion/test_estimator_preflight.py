"""The hover thrust is estimated before our first command flies (issue 12).

Before OFFBOARD, PX4's own mode flies the vehicle with its own (converged) hover thrust and
streams that thrust setpoint in ATTITUDE_TARGET. The pipeline feeds it to the offset-free
estimator, so a companion configured 30 % off knows the true hover thrust when OFFBOARD starts;
without the stream, on the ground, from another system, or with a stale setpoint, the estimate
must not move (the prior stays the configured value).

The vehicle here is the translational model the estimator assumes, written out (a hover at the
true thrust holds the velocity at zero): the pipeline must reach the true value from telemetry
alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import load_config
from companion.control.pipeline import ControlPipeline
from companion.control.telemetry import TelemetryStore
from companion.control.wiring import new_store

H_TRUE = 0.5
AUTOPILOT = 1  # [mavlink] target_system of the default config
PX4_POSCTL = (3 << 16)  # custom_mode: main mode POSCTL


class _NoPerception:
    def process(self, image: object) -> None:  # pragma: no cover - never called (no image)
        return None


class _NoSolver:
    def solve(self, *a: object) -> None:  # pragma: no cover - no target, never solved
        raise AssertionError("no solve without a target")


def _pipeline(h_cfg: float, *overrides: str) -> tuple[ControlPipeline, TelemetryStore]:
    cfg = load_config(overrides=[f"control.hover_thrust={h_cfg}", *overrides])
    return ControlPipeline(cfg, _NoPerception(), rmpc=_NoSolver()), new_store(cfg)  # type: ignore[arg-type]


def _feed(store: TelemetryStore, t: float, thrust: float, *, landed_state: int = 2,
          sysid: int = AUTOPILOT, attitude_target: bool = True) -> None:
    """PX4 hovering in POSCTL at ``t``: attitude (level), velocity, its thrust setpoint."""
    store.ingest("HEARTBEAT", {"custom_mode": PX4_POSCTL, "base_mode": 128 | 1}, t, AUTOPILOT)
    store.ingest("EXTENDED_SYS_STATE", {"landed_state": landed_state}, t, sysid)
    store.ingest("ATTITUDE_QUATERNION", {"q1": 1.0, "q2": 0.0, "q3": 0.0, "q4": 0.0,
                                         "yawspeed": 0.0}, t, AUTOPILOT)
    # the true vehicle: v' = g - g T / h_true (level); at T = h_true it holds still
    vz = 9.81 * (1.0 - thrust / H_TRUE) * t
    store.ingest("LOCAL_POSITION_NED", {"x": 0.0, "y": 0.0, "z": -2.0, "vx": 0.0, "vy": 0.0,
                                        "vz": vz}, t, AUTOPILOT)
    if attitude_target:
        store.ingest("ATTITUDE_TARGET", {"thrust": thrust, "q": [1.0, 0.0, 0.0, 0.0]}, t,
                     sysid)


def _preflight(pipe: ControlPipeline, store: TelemetryStore, seconds: float = 1.0,
               **kw: object) -> float:
    """PX4 flies at the true hover thrust; the companion steps at 20 Hz, not in control."""
    t = 0.0
    while t < seconds:
        for k in range(3):  # telemetry at 60 Hz between frames
            _feed(store, t + k / 60.0, H_TRUE, **kw)  # type: ignore[arg-type]
        t += 0.05
        res = pipe.step(None, t, store, t_now_s=t, in_control=False)
    assert res.estimator is not None
    return res.estimator.hover_thrust


@pytest.mark.parametrize("h_cfg", [0.35, 0.65])
def test_the_autopilots_own_hover_is_learnt_before_offboard(h_cfg: float) -> None:
    pipe, store = _pipeline(h_cfg)
    assert _preflight(pipe, store) == pytest.approx(H_TRUE, abs=0.01)


@pytest.mark.parametrize("why", ["switched off", "on the ground", "other system", "no stream"])
def test_the_prior_is_kept_without_a_usable_autopilot_thrust(why: str) -> None:
    over = ["control.estimator.autopilot_thrust=false"] if why == "switched off" else []
    pipe, store = _pipeline(0.35, *over)
    kw: dict[str, object] = {}
    if why == "on the ground":
        kw["landed_state"] = 1
    elif why == "other system":
        kw["sysid"] = 42
    elif why == "no stream":
        kw["attitude_target"] = False
    assert _preflight(pipe, store, **kw) == pytest.approx(0.35)


def test_autopilot_thrust_is_time_weighted_and_refused_when_stale() -> None:
    store = new_store(load_config())
    store.ingest("EXTENDED_SYS_STATE", {"landed_state": 2}, 0.0, AUTOPILOT)
    for t, thr in ((0.0, 0.4), (0.1, 0.6)):
        assert store.ingest("ATTITUDE_TARGET", {"thrust": thr}, t, AUTOPILOT)
    assert store.autopilot_thrust_over(0.05, 0.15) == pytest.approx(0.5)
    assert store.autopilot_thrust_over(0.5, 0.6, max_age_s=0.25) is None  # 0.4 s old
    assert store.autopilot_thrust_over(-0.1, 0.0) is None  # nothing in force yet
    for bad in (float("nan"), -0.1, 1.5):
        assert not store.ingest("ATTITUDE_TARGET", {"thrust": bad}, 0.2, AUTOPILOT)
    assert not store.ingest("ATTITUDE_TARGET", {"thrust": 0.5}, 0.05, AUTOPILOT)  # out of order
    assert [s.thrust_norm for s in store.thrust_setpoints] == [0.4, 0.6]
    assert np.isfinite(store.autopilot_thrust_over(0.1, 0.2) or np.nan)
