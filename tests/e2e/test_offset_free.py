"""Offset-free tracking and latency compensation, flown end to end (emulator + companion
processes in lockstep, scored from the emulator's ground truth).

- The companion's hover thrust 30 % off the emulator's 0.5 (0.35 and 0.65): with the estimator
  no solver failure, no fallback, the target never lost, and the estimate ends at the truth;
  without it the flight breaks down as the issue reports (measured here, so the test can fail).
- A constant 0.5 m/s^2 wind: the steady horizontal offset with the estimator is a small
  fraction of the one without.
- The realistic world (config/realistic.toml) with its stiffer RMPC tuning: within 10 mm RMS
  after settling in both axes.
- 60 +- 15 ms camera latency on `edge`: with the compensation every corner stays inside the
  500 px area and the target is never lost.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.reader import LogReader

pytestmark = pytest.mark.slow


# The emulator waits this long (wall time) for each setpoint: on a loaded machine a step of
# the companion can take longer than the default 0.5 s, and the flight would stop being
# lockstep (frames dropped, setpoints applied late). These tests judge the control.
PATIENT = "[sim]\nlockstep_timeout_s = 10.0\n"


def _variant(tmp: Path, body: str) -> Path:
    p = tmp / "sim.toml"
    p.write_text(f'base = "{DEFAULT_CONFIG}"\n{PATIENT}{body}\n')
    return p


def _fly(tmp: Path, scenario: str, duration: float, overrides: list[str],
         sim_body: str | None = None, min_share: float = 0.9) -> dict[str, Any]:
    tmp.mkdir(parents=True, exist_ok=True)
    sim = _variant(tmp, sim_body or "")
    rep = run_demo(DEFAULT_CONFIG, scenario, duration, tmp, overrides, [], plots=False,
                   sim_config=sim)
    with LogReader(tmp / "flight.mcap") as r:
        rep["_steps"] = [m.data for m in r.messages(topics=["/control/step"]) if m.data]
        rep["_truth"] = [m.data for m in r.messages(topics=["/truth"]) if m.data]
    assert len(rep["_steps"]) > min_share * duration * 20, "the flight did not run"
    return rep


def _last_horizontal_m(rep: dict[str, Any], window_s: float) -> float:
    rows = [(r["t_us"] * 1e-6, np.hypot(*(np.array(r["agv"]["pos_ned_m"][:2])
                                          - np.array(r["uav"]["pos_ned_m"][:2]))))
            for r in rep["_truth"] if r.get("uav") and r.get("agv")]
    t_end = rows[-1][0]
    return float(np.sqrt(np.mean([e * e for t, e in rows if t >= t_end - window_s])))


@pytest.mark.parametrize("hover", [0.35, 0.65])
def test_wrong_hover_thrust_is_estimated_in_flight(tmp_path: Path, hover: float) -> None:
    rep = _fly(tmp_path, "paper", 15.0, [f"control.hover_thrust={hover}"])
    sol, vis = rep["solver"], rep["visibility"]
    assert sol["failures"] == 0 and sol["fallbacks"] == 0, sol
    assert vis["frames_target_lost"] == 0, vis
    levels = {s["safety"]["level"] for s in rep["_steps"]}
    assert levels == {"tracking"}, levels
    est = [s["estimator"] for s in rep["_steps"] if s.get("estimator")]
    assert est and est[-1]["hover_thrust"] == pytest.approx(0.5, abs=0.01)
    assert all(math.isfinite(e["hover_thrust"]) and 0.2 <= e["hover_thrust"] <= 0.8
               for e in est)
    for s in rep["_steps"]:
        sp = s.get("setpoint")
        assert sp is None or all(math.isfinite(x) for x in [*sp["q_wxyz"], sp["thrust"]])


def test_without_the_estimator_a_wrong_hover_thrust_breaks_the_flight(tmp_path: Path) -> None:
    """The issue's measurement, kept as the baseline the estimator is judged against."""
    rep = _fly(tmp_path, "paper", 15.0,
               ["control.hover_thrust=0.35", "control.estimator.enabled=false"])
    bad = rep["solver"]["failures"] + rep["visibility"]["frames_target_lost"]
    assert bad > 0, (rep["solver"], rep["visibility"])


HOVER_START = "[sim.scenarios.hover]\nuav_pose = [0.0, 0.0, -2.0, 0.0, 0.0, 0.0]"


def _max_height_error_m(rep: dict[str, Any]) -> float:
    return max(abs((r["agv"]["pos_ned_m"][2] - r["uav"]["pos_ned_m"][2]) - 2.0)
               for r in rep["_truth"] if r.get("uav") and r.get("agv"))


def test_the_hover_thrust_is_known_before_offboard(tmp_path: Path) -> None:
    """Started at the set point with the hover thrust 30 % off: PX4's own thrust before
    OFFBOARD (ATTITUDE_TARGET) gives the estimate, so the first command of ours is flown at the
    right thrust and the height never leaves 2 cm. Without it (the estimate starts with our
    first command) the first 50 ms at the wrong thrust cost more than 2 cm (measured here, so
    the test can fail)."""
    on = _fly(tmp_path / "on", "hover", 8.0, ["control.hover_thrust=0.35"], HOVER_START)
    first = next(s for s in on["_steps"] if s.get("in_control"))
    assert first["estimator"]["hover_thrust"] == pytest.approx(0.5, abs=0.01), first
    assert _max_height_error_m(on) < 0.02
    assert on["solver"]["failures"] == 0 and on["visibility"]["frames_target_lost"] == 0
    off = _fly(tmp_path / "off", "hover", 8.0,
               ["control.hover_thrust=0.35", "control.estimator.autopilot_thrust=false"],
               HOVER_START)
    assert _max_height_error_m(off) > 0.05


def test_a_steady_wind_is_rejected(tmp_path: Path) -> None:
    wind = "[sim.disturbance]\nwind_accel_ned_m_s2 = [0.4, 0.3, 0.0]"
    on = _fly(tmp_path / "on", "paper", 20.0, [], wind)
    off = _fly(tmp_path / "off", "paper", 20.0, ["control.estimator.enabled=false"], wind)
    e_on, e_off = _last_horizontal_m(on, 5.0), _last_horizontal_m(off, 5.0)
    assert e_on < 0.02, e_on
    assert e_on < 0.1 * e_off, (e_on, e_off)
    d = on["_steps"][-1]["estimator"]["d_ned_m_s2"]
    # the estimate is the wind plus the emulator's drag on the AGV's speed: close to 0.5
    assert math.hypot(d[0], d[1]) == pytest.approx(0.5, abs=0.1)


def test_the_realistic_world_is_held_within_a_centimetre(tmp_path: Path) -> None:
    """config/realistic.toml (PX4's cascade, turbulence, wind, a hover thrust 15 % off, the
    realistic camera and telemetry) with its stiffer RMPC tuning: after settling the vehicle
    stays within 10 mm RMS of the set point in both axes (the paper's weights: ~15 mm
    horizontally, docs/records/2026-11-offset-free.md section 3), the target in view, no
    fallback."""
    realistic = DEFAULT_CONFIG.parent / "realistic.toml"
    sim = tmp_path / "sim.toml"
    sim.write_text(f'base = "{realistic}"\n{PATIENT}')
    rep = run_demo(realistic, "paper", 30.0, tmp_path, [], [], plots=False, sim_config=sim)
    trk = rep["tracking"]
    assert trk["settle_time_s"] is not None and trk["settle_time_s"] < 12.0, trk
    assert trk["rms_horizontal_error_after_settle_m"] <= 0.010, trk
    assert trk["rms_height_error_after_settle_m"] <= 0.010, trk
    assert rep["visibility"]["frames_target_lost"] == 0
    assert rep["solver"]["failures"] == 0 and rep["solver"]["fallbacks"] == 0, rep["solver"]


@pytest.fixture(scope="module")
def latency_flight(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    lat = "[sim.camera_model]\nlatency_ms = 60.0\nlatency_jitter_ms = 15.0"
    # "the flight ran" only: with 60 +- 15 ms of camera latency the 6 s flight steps on 108-115
    # of its 120 frames (six runs, 2026-11-28: the jittered frames overtake each other and the
    # newest is answered), so 0.9 (108) sat on that spread's edge and failed once in CI at 108
    return _fly(tmp_path_factory.mktemp("latency"), "edge", 6.0, [], lat, min_share=0.8)


def test_camera_latency_edge_keeps_the_target_in_view(latency_flight: dict[str, Any]) -> None:
    vis = latency_flight["visibility"]
    assert max(vis["max_abs_u_px"], vis["max_abs_n_px"]) < 500.0, vis
    assert vis["frames_target_lost"] == 0
    ages = [s["latency"]["frame_age_s"] for s in latency_flight["_steps"] if s.get("latency")]
    # the companion measures the frames' age on the autopilot clock and predicts across it
    assert ages and min(ages) >= 0.045


def test_lockstep_frames_reach_the_companion_within_the_configured_latency(
        latency_flight: dict[str, Any]) -> None:
    """The emulator's lockstep waits for one answer per delivered frame (two when the jitter
    delivers two in a step), so no frame reaches the companion later than its latency step."""
    ages = [s["t_now_s"] - s["frame_t_us"] * 1e-6 for s in latency_flight["_steps"]]
    assert max(ages) <= 0.105, max(ages)


def test_a_biased_accelerometer_is_fused_in_flight(tmp_path: Path) -> None:
    """HIGHRES_IMU over real UDP into the estimator (``control.estimator.accelerometer``): a
    steady wind and an accelerometer biased by (0.2, -0.1) m/s^2 in body x/y. Every sample
    reaches the filter (the default world's streams are sampled at the 20 Hz step boundaries),
    the bias state finds the bias, and the wind estimate is where the velocity puts it (the
    bias does not leak into it); the flight tracks as without the accelerometer."""
    body = ("[sim.disturbance]\nwind_accel_ned_m_s2 = [0.4, 0.3, 0.0]\n"
            "[sim.telemetry]\naccel_bias_m_s2 = [0.2, -0.1, 0.0]")
    rep = _fly(tmp_path, "paper", 15.0, ["control.estimator.accelerometer=true"], body)
    assert rep["solver"]["failures"] == 0 and rep["visibility"]["frames_target_lost"] == 0
    est = [s["estimator"] for s in rep["_steps"] if s.get("estimator")]
    last = est[-1]
    assert last["accel_updates"] > 0.8 * 13.0 * 20, last["accel_updates"]
    assert last["reason"] == "" and last["rejected"] == 0
    assert last["accel_bias_m_s2"] == pytest.approx([0.2, -0.1], abs=0.05)
    d = last["d_ned_m_s2"]
    assert math.hypot(d[0], d[1]) == pytest.approx(0.5, abs=0.1)
    assert _last_horizontal_m(rep, 5.0) < 0.02
