"""Safety fallbacks, driven through the emulator (lockstep flights over real sockets).

Each flight injects one fault in a time window (the emulator's ``[sim.faults]`` and camera
occlusions, or the companion's solver fault injection) and checks: the right fallback level
during the fault, never a NaN on the wire, and tracking again afterwards.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.commands.demo import run_demo
from companion.config import DEFAULT_CONFIG
from companion.core.disturbance import compensated_input
from companion.core.setpoint import attitude_setpoint
from companion.log.reader import LogReader

pytestmark = pytest.mark.slow

DURATION_S = 8.0


def _fly(tmp: Path, sim_extra: str = "", faults: tuple[str, ...] = (),
         duration_s: float = DURATION_S) -> list[dict]:
    sim_cfg = None
    if sim_extra:
        sim_cfg = tmp / "sim.toml"
        sim_cfg.write_text(f'base = "{DEFAULT_CONFIG}"\n{sim_extra}\n')
    run_demo(DEFAULT_CONFIG, "paper", duration_s, tmp, [], list(faults), plots=False,
             sim_config=sim_cfg)
    with LogReader(tmp / "flight.mcap") as r:
        wire = [m.data["fields"] for m in r.messages(topics=["/mavlink/out/SET_ATTITUDE_TARGET"])]
        steps = [m.data for m in r.messages(topics=["/control/step"])]
    for f in wire:  # never a NaN on the wire, whatever happened
        assert all(math.isfinite(v) for v in [*f["q"], f["thrust"]]), f
        assert f["type_mask"] == 7
    assert steps
    return steps


def _levels(steps: list[dict], t0: float, t1: float) -> set[str]:
    return {s["safety"]["level"] for s in steps if t0 <= s["t_s"] < t1}


def _level_hover(steps: list[dict], t0: float, t1: float) -> None:
    """The hover setpoint holds the vehicle still: zero acceleration through the offset-free
    estimate logged with the step (docs/reference/estimator.md), i.e. nearly level at ~0.5 here."""
    for s in steps:
        if t0 <= s["t_s"] < t1 and s["safety"]["level"] == "hover":
            sp = s["setpoint"]
            est = s["estimator"]
            want = attitude_setpoint(
                compensated_input(np.zeros(4), est["d_ned_m_s2"], sp["yaw_rad"]),
                sp["yaw_rad"], 0.0, hover_thrust=est["hover_thrust"], thrust_min=0.05,
                thrust_max=0.95)
            assert sp["roll_rad"] == pytest.approx(want.roll_rad, abs=1e-9)
            assert sp["pitch_rad"] == pytest.approx(want.pitch_rad, abs=1e-9)
            assert sp["thrust"] == pytest.approx(want.thrust_norm, abs=1e-9)
            assert abs(sp["roll_rad"]) < 0.02 and abs(sp["pitch_rad"]) < 0.02
            assert sp["thrust"] == pytest.approx(0.5, abs=0.01)


def test_stale_telemetry_gives_level_hover_then_recovers(tmp_path: Path) -> None:
    steps = _fly(tmp_path, "[sim.faults]\ntelemetry_dropouts = [[4.0, 5.0]]")
    assert _levels(steps, 3.0, 4.0) == {"tracking"}
    during = _levels(steps, 4.3, 5.0)
    assert during == {"hover"}, during  # no state from stale data: straight to level hover
    _level_hover(steps, 4.3, 5.0)
    assert _levels(steps, 5.5, DURATION_S) == {"tracking"}


def test_nan_telemetry_is_refused_and_treated_as_missing(tmp_path: Path) -> None:
    steps = _fly(tmp_path, "[sim.faults]\ntelemetry_nan = [[4.0, 4.8]]")
    during = _levels(steps, 4.3, 4.8)
    assert during == {"hover"}, during
    _level_hover(steps, 4.3, 4.8)
    assert _levels(steps, 5.3, DURATION_S) == {"tracking"}
    with LogReader(tmp_path / "flight.mcap") as r:
        rejected = [m.data for m in r.messages(topics=["/mavlink/rejected"])]
    assert any(d.get("reason") == "non_finite" for d in rejected)


def test_occluded_target_reacquires_with_follow_target(tmp_path: Path) -> None:
    steps = _fly(tmp_path, "[sim.camera]\nocclusions = [[4.0, 5.0]]")
    during = [s for s in steps if 4.0 <= s["t_s"] < 5.0]
    assert all(s["perception"]["status"] != "ok" for s in during)
    # FOLLOW_TARGET is fresh: keep following its predicted position (after the short
    # target-lost timeout), climbing to widen the view -- not a blind hover
    levels = _levels(steps, 4.55, 5.0)
    assert levels == {"reacquire"}, levels
    climbing = [s for s in during if s["safety"]["level"] == "reacquire"]
    assert climbing and all(s["u"][2] < 0 for s in climbing)  # r3 < 0: up (NED)
    assert _levels(steps, 5.2, DURATION_S) == {"tracking"}


def test_solver_failure_falls_back_to_terminal_law_then_hover_then_recovers(
    tmp_path: Path,
) -> None:
    steps = _fly(tmp_path, faults=("solver:3.0:5.0",))
    t_first = steps[0]["t_s"]
    fault = [s for s in steps if 3.0 <= s["t_s"] - t_first < 5.0]
    assert all(s["rmpc"]["mode"] == "fallback" for s in fault if s["rmpc"])
    t_a = t_first + 3.0
    assert _levels(steps, t_a + 0.05, t_a + 0.95) == {"terminal"}
    assert _levels(steps, t_a + 1.05, t_a + 1.95) == {"hover"}
    _level_hover(steps, t_a + 1.05, t_a + 1.95)
    assert _levels(steps, t_a + 2.1, t_first + DURATION_S) == {"tracking"}


def test_a_stuck_solver_is_cut_and_the_companion_keeps_flying(tmp_path: Path) -> None:
    """``solver-hang``: each solve in the window never returns (the solver process's test
    hook: 100 % CPU, SIGTERM ignored). The step is abandoned after rmpc.max_solve_time_s
    with a 'timeout' fallback, the loop keeps stepping (a command on the wire every step the
    ladder does not silence, never a NaN), and once the new solver process has loaded the
    RMPC solves again. In lockstep the restart (~1 s of wall time) spans several simulated
    seconds, since the fallback steps are fast: the ladder may reach hover or silence meanwhile;
    on a real vehicle it is ~15-20 steps of terminal law."""
    steps = _fly(tmp_path, faults=("solver-hang:3.0:3.2",), duration_s=14.0)
    t_first = steps[0]["t_s"]
    statuses = [(s["t_s"] - t_first, s["rmpc"]) for s in steps if s["rmpc"]]
    timeouts = [t for t, r in statuses if r["status"].startswith("timeout:")]
    assert timeouts and all(3.0 <= t < 3.3 for t in timeouts)
    after = [r for t, r in statuses if t > timeouts[0]]
    first_ok = next(i for i, r in enumerate(after) if r["mode"] == "optimal")
    assert all(r["mode"] == "fallback"
               and r["status"].startswith(("timeout:", "solver restarting"))
               for r in after[:first_ok])
    assert all(np.all(np.isfinite(r["u0"])) for _, r in statuses)
    for s in steps:  # a silent step is the ladder's choice; every other step sent its command
        assert s["sent"] or s["safety"]["level"] == "silent"
    assert {r["mode"] for t, r in statuses if t > timeouts[-1] + 1e-9}.issuperset({"optimal"})


def test_the_autopilot_failsafe_after_our_silence_is_reported(tmp_path: Path) -> None:
    """Telemetry gone for good: level hover, then silence (safety.silence_after_s); PX4 leaves
    OFFBOARD COM_OF_LOSS_T later and reports the failsafe in its HEARTBEAT (system_status
    CRITICAL, HEARTBEAT.hpp); the companion logs that on /control/safety."""
    # lockstep steps without our setpoint wait lockstep_timeout_s of wall time each: short here
    _fly(tmp_path, "[sim]\nlockstep_timeout_s = 0.05\n[sim.faults]\n"
         "telemetry_dropouts = [[3.0, 30.0]]", duration_s=9.0)
    with LogReader(tmp_path / "flight.mcap") as r:
        beats = [(m.log_time_ns, m.data["fields"]) for m in
                 r.messages(topics=["/mavlink/in/HEARTBEAT"])]
        texts = [(m.log_time_ns, m.data["message"]) for m in
                 r.messages(topics=["/control/safety"])]
    critical = [t for t, b in beats if b["system_status"] == 5]
    assert critical, [b["system_status"] for _, b in beats]
    assert all((b["custom_mode"] >> 16) & 0xFF != 6 for t, b in beats if t >= critical[0])
    said = [(t, m) for t, m in texts if "autopilot system status ACTIVE -> CRITICAL" in m]
    assert len(said) == 1 and said[0][0] >= critical[0]
