"""Offboard state machine and safety supervisor: pure logic driven with explicit time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion import ConfigError
from companion.config import OffboardConfig, SafetyConfig, load_config
from companion.control.offboard import (
    MAV_LANDED_STATE_IN_AIR as IN_AIR,
)
from companion.control.offboard import (
    OffboardManager,
    OffboardPhase,
    VehicleStatus,
)
from companion.control.safety import Health, SafetyLevel, SafetySupervisor

OFF = OffboardConfig(preflight_stream_s=1.0, mode_retry_s=1.0, arm=True, exit_mode="hold")
SAFE = SafetyConfig(
    telemetry_timeout_s=0.2, target_lost_timeout_s=0.5, follow_target_timeout_s=1.0,
    hover_fallback_s=1.0, silence_after_s=3.0, reacquire_climb_rate_m_s=0.3,
    reacquire_max_height_m=4.0,
)


def _hb(t: float, armed: bool, main: int, sub: int = 0) -> VehicleStatus:
    return VehicleStatus(armed=armed, main_mode=main, sub_mode=sub, t_s=t)


def test_offboard_waits_for_preflight_stream_then_arms_then_requests_and_confirms() -> None:
    m = OffboardManager(OFF)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, False, 3))
    acts_before = []
    t = 0.0
    while t < 0.99:  # streaming for less than 1 s: nothing may be requested
        m.on_streamed(t)
        acts_before += m.step(t)
        t += 0.05
    assert acts_before == [] and m.phase is OffboardPhase.PREFLIGHT
    m.on_streamed(1.0)
    assert [a.kind for a in m.step(1.0)] == ["arm"]
    assert m.step(1.5) == []  # retry only after mode_retry_s
    assert [a.kind for a in m.step(2.0)] == ["arm"]
    m.on_heartbeat(_hb(2.1, True, 3))
    acts = m.step(2.1)
    assert [(a.kind, a.main_mode) for a in acts] == [("set_mode", 6)]
    # rejected (mode unchanged): retried after mode_retry_s, not before
    assert m.step(2.5) == []
    assert [a.kind for a in m.step(3.2)] == ["set_mode"]
    m.on_heartbeat(_hb(3.3, True, 6))
    assert m.phase is OffboardPhase.ACTIVE
    assert m.step(3.4) == []


def _stream(m: OffboardManager, t0: float, t1: float, escaping: bool) -> list[tuple[float, str]]:
    """Stream one setpoint every 50 ms over [t0, t1) with the controller's verdict; actions."""
    out = []
    t = t0
    while t < t1 - 1e-9:
        m.on_streamed(t)
        m.on_controller(escaping)
        out += [(round(t, 3), a.kind) for a in m.step(t)]
        t += 0.05
    return out


def test_an_escaping_target_cuts_the_preflight_stream_to_the_escape_time() -> None:
    cfg = OffboardConfig(preflight_stream_s=1.0, mode_retry_s=1.0, arm=False, exit_mode="hold",
                         preflight_escape_stream_s=0.25)
    # the controller's hard problem infeasible throughout: requested at 0.25 s, not at 1 s
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    assert _stream(m, 0.0, 1.2, escaping=True) == [(0.25, "set_mode")]
    assert m.phase is OffboardPhase.REQUESTING
    assert "target escaping" in m.transitions[-1][2]
    # feasible throughout: the full stream
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    assert _stream(m, 0.0, 1.2, escaping=False) == [(1.0, "set_mode")]
    assert m.transitions[-1][2] == "pre-flight stream done"
    # infeasible only once the stream is 0.6 s old: requested then (the stream is long enough)
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    acts = _stream(m, 0.0, 0.6, escaping=False) + _stream(m, 0.6, 1.2, escaping=True)
    assert acts == [(0.6, "set_mode")]
    # infeasible, then feasible again before 0.25 s: no early request
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    acts = _stream(m, 0.0, 0.2, escaping=True) + _stream(m, 0.2, 1.2, escaping=False)
    assert acts == [(1.0, "set_mode")]
    # without the key (None), an escaping target waits for the full stream
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    assert _stream(m, 0.0, 1.2, escaping=True) == [(1.0, "set_mode")]
    # a pause in the stream longer than STREAM_GAP_S (safety silence) restarts the clock for
    # the cut stream as well
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    assert _stream(m, 0.0, 0.2, escaping=True) == []
    m.on_stream_gap()
    assert _stream(m, 0.8, 1.0, escaping=True) == []
    assert _stream(m, 1.0, 1.1, escaping=True) == [(1.05, "set_mode")]


def test_a_short_pause_in_the_stream_keeps_the_preflight_stream() -> None:
    """A stale frame (one missing setpoint) is no loss of PX4's offboard signal
    (COM_OF_LOSS_T 1 s): the 1 s stream is not restarted; a pause beyond STREAM_GAP_S is."""
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    acts = []
    for k in range(0, 24):
        t = 0.05 * k
        if k % 3 == 1:  # every third setpoint missing
            m.on_stream_gap()
            continue
        m.on_streamed(t)
        acts += [(round(t, 2), a.kind) for a in m.step(t)]
    assert acts[:1] == [(1.0, "set_mode")]
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    m.on_streamed(0.0)
    assert m.step(0.0) == []
    # 0.6 s without a setpoint: the stream starts over at 0.6 and is long enough at 1.6
    assert _stream(m, 0.6, 1.65, escaping=False) == [(1.6, "set_mode")]


def test_an_escape_stream_longer_than_the_stream_is_refused() -> None:
    with pytest.raises(ConfigError, match="preflight_escape_stream_s"):
        OffboardConfig(1.0, 1.0, False, "hold", preflight_escape_stream_s=1.5)


def test_offboard_lost_does_not_fight_pilot_unless_reengage() -> None:
    for reengage in (False, True):
        m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"), reengage=reengage)
        m.on_landed_state(IN_AIR)
        m.on_heartbeat(_hb(0.0, True, 3))
        m.on_streamed(0.0)
        m.step(1.0)
        m.on_heartbeat(_hb(1.1, True, 6))
        assert m.phase is OffboardPhase.ACTIVE
        m.on_heartbeat(_hb(2.0, True, 3))  # failsafe / pilot -> Position
        assert m.phase is OffboardPhase.LOST
        acts = m.step(2.1)
        assert (acts != []) is reengage


def test_offboard_exit_requests_hold_then_stops_streaming() -> None:
    m = OffboardManager(OffboardConfig(0.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 6))
    m.on_streamed(0.0)
    m.step(0.0)
    m.request_exit(5.0)
    acts = m.step(5.0)
    assert [(a.kind, a.main_mode, a.sub_mode) for a in acts] == [("set_mode", 4, 3)]
    m.on_heartbeat(_hb(5.2, True, 4, 3))
    assert [a.kind for a in m.step(5.3)] == ["stop_stream"]


def _h(t: float, tel: float = 0.0, tgt: float = 0.0, fol: float = math.inf,
       finite: bool = True, solver: bool = True) -> Health:
    return Health(t, tel, tgt, fol, finite, solver)


def test_safety_fallback_order_and_recovery() -> None:
    s = SafetySupervisor(SAFE)
    assert s.update(_h(0.0)).level is SafetyLevel.TRACKING
    # solver failure with valid state: terminal law, then hover, then silence
    assert s.update(_h(1.0, solver=False)).level is SafetyLevel.TERMINAL
    assert s.update(_h(1.9, solver=False)).level is SafetyLevel.TERMINAL
    assert s.update(_h(2.0, solver=False)).level is SafetyLevel.HOVER
    assert s.update(_h(3.99, solver=False)).level is SafetyLevel.HOVER
    d = s.update(_h(4.0, solver=False))
    assert d.level is SafetyLevel.SILENT and d.changed and "solver failed" in d.reason
    # healthy again: straight back to tracking
    assert s.update(_h(4.05)).level is SafetyLevel.TRACKING


def test_safety_never_uses_state_built_from_bad_data() -> None:
    for bad in (_h(0.0, tel=0.5), _h(0.0, finite=False), _h(0.0, tgt=0.6)):
        s = SafetySupervisor(SAFE)
        d = s.update(bad)
        assert d.level is SafetyLevel.HOVER, bad
        assert not s.state_valid(bad)


def test_safety_reacquires_with_fresh_follow_target() -> None:
    s = SafetySupervisor(SAFE)
    assert s.update(_h(0.0, tgt=0.6, fol=0.1)).level is SafetyLevel.REACQUIRE
    # FOLLOW_TARGET goes stale too: no guess, hover
    assert s.update(_h(0.1, tgt=0.7, fol=1.5)).level is SafetyLevel.HOVER
    assert s.update(_h(0.2, tgt=0.0, fol=1.5)).level is SafetyLevel.TRACKING


def test_a_refused_offboard_request_does_not_count_as_control_until_the_next_one() -> None:
    m = OffboardManager(OffboardConfig(0.25, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    m.on_streamed(0.0)
    assert m.step(0.2) == [] and not m.awaiting_switch
    assert [(a.kind, a.main_mode) for a in m.step(0.25)] == [("set_mode", 6)]
    assert m.awaiting_switch  # PX4 switches on the request: our setpoints fly from here
    m.on_command_ack(400, 1, 0.3)  # another command's ACK changes nothing
    assert m.awaiting_switch
    m.on_command_ack(176, 1, 0.3)  # TEMPORARILY_REJECTED: PX4 did not switch
    assert m.phase is OffboardPhase.REQUESTING and not m.awaiting_switch
    assert m.step(0.8) == []  # retried after mode_retry_s, not before
    assert [a.kind for a in m.step(1.25)] == ["set_mode"]
    assert m.awaiting_switch
    m.on_command_ack(176, 0, 1.3)
    assert m.awaiting_switch
    m.on_heartbeat(_hb(1.4, True, 6))
    assert m.phase is OffboardPhase.ACTIVE


@pytest.mark.parametrize(("override", "message"), [
    ("offboard.preflight_escape_stream_s=2.0", "must not exceed offboard.preflight_stream_s"),
    ("offboard.preflight_escape_stream_s=-0.1", "offboard.preflight_escape_stream_s: "),
    ('offboard.preflight_escape_stream_s="soon"', "must be a number"),
    ("offboard.preflight_escape_stream_s=nan", "must be finite"),
])
def test_a_bad_escape_stream_in_the_config_file_is_a_clear_error(override: str,
                                                                  message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=[override])


def test_the_escape_stream_is_read_from_the_config_file() -> None:
    assert load_config().offboard.preflight_escape_stream_s == 0.15
    assert load_config(overrides=["offboard.preflight_escape_stream_s=0.5"]
                       ).offboard.preflight_escape_stream_s == 0.5


def test_without_arming_offboard_waits_for_the_pilot_to_arm() -> None:
    """offboard.arm = false (a real vehicle): a disarmed vehicle is never asked for OFFBOARD,
    however long the stream; once the HEARTBEAT says armed, the request follows."""
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, False, 3))
    assert _stream(m, 0.0, 3.0, escaping=False) == []
    assert m.phase is OffboardPhase.PREFLIGHT
    m.on_heartbeat(_hb(3.0, True, 3))
    assert _stream(m, 3.0, 3.1, escaping=False) == [(3.0, "set_mode")]


@pytest.mark.parametrize("landed", [None, 1, 3, 4])
@pytest.mark.parametrize("arm", [True, False])
def test_offboard_is_not_requested_nor_armed_until_the_vehicle_is_in_the_air(
        landed: int | None, arm: bool) -> None:
    """offboard.require_in_air (default): on the ground, taking off, landing or with no
    EXTENDED_SYS_STATE heard, neither arming nor OFFBOARD is asked for, however long the
    stream; the held-back reason names the state and the key; IN_AIR releases the request."""
    m = OffboardManager(OffboardConfig(1.0, 1.0, arm, "hold"))
    if landed is not None:
        m.on_landed_state(landed)
    m.on_heartbeat(_hb(0.0, not arm, 3))
    acts = []
    for i in range(100):
        t = 0.05 * i
        m.on_streamed(t)
        acts += m.step(t)
    assert acts == [] and m.phase is OffboardPhase.PREFLIGHT
    assert m.held is not None and "offboard.require_in_air" in m.held
    assert ("not reported yet" if landed is None else
            {1: "ON_GROUND", 3: "TAKEOFF", 4: "LANDING"}[landed]) in m.held
    m.on_landed_state(IN_AIR)
    m.on_streamed(5.0)
    assert [a.kind for a in m.step(5.0)] == (["arm"] if arm else ["set_mode"])
    assert m.held is None


def test_require_in_air_false_asks_on_the_ground() -> None:
    cfg = OffboardConfig(1.0, 1.0, False, "hold", require_in_air=False)
    m = OffboardManager(cfg)
    m.on_landed_state(1)
    m.on_heartbeat(_hb(0.0, True, 3))
    for i in range(21):
        m.on_streamed(0.05 * i)
    assert [a.kind for a in m.step(1.0)] == ["set_mode"] and m.held is None


def test_reengage_waits_for_the_air_too() -> None:
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"), reengage=True)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(0.0, True, 3))
    for i in range(21):
        m.on_streamed(0.05 * i)
    assert [a.kind for a in m.step(1.0)] == ["set_mode"]
    m.on_heartbeat(_hb(1.1, True, 6))
    assert m.phase is OffboardPhase.ACTIVE
    m.on_heartbeat(_hb(2.0, True, 3))  # the pilot (or a failsafe) took over
    assert m.phase is OffboardPhase.LOST
    m.on_landed_state(1)  # and landed
    for i in range(60):
        m.on_streamed(2.0 + 0.05 * i)
        assert m.step(2.0 + 0.05 * i) == []
    assert m.held is not None and "ON_GROUND" in m.held


@pytest.mark.parametrize("phase_s", [0.0, 0.002, 0.005, 0.008])
def test_the_shipped_escape_stream_meets_px4s_10_hz_check(phase_s: float) -> None:
    """The shipped ``preflight_escape_stream_s`` against the emulated PX4, which judges a
    DO_SET_MODE on its last health check, run at 10 Hz in a 10 ms commander loop and at once
    when a setpoint arrives while the signal is lost (docs/reference/px4-offboard.md section 2):
    whatever the phase of PX4's loop and checks
    against our 20 Hz stream, with the camera's latency 15 ms longer for the first frame than
    for the rest (a stream measured in frame time, sent 30 ms shorter) and the request up to
    10 ms faster on the link than the first setpoint, the first request
    is accepted (a refused one waits mode_retry_s, 1 s, while the target escapes)."""
    from sim_bridge.physics.vehicle import initial_state
    from sim_bridge.px4 import ACCEPTED, AttitudeTarget, Mode, Px4, Px4Params

    cfg = load_config().offboard
    sp = AttitudeTarget(7, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.5)
    for start_s in np.arange(0.0, 0.1, 0.01):  # the stream's start against PX4's check grid
        for jitter_s, cmd_ahead_s in ((0.0, 0.0), (0.0, 0.01), (0.015, 0.0), (0.015, 0.01)):
            px4 = Px4(Px4Params(), initial_state((0, 0, -3.0)), armed=True)
            m = OffboardManager(cfg)
            m.on_landed_state(IN_AIR)
            m.on_heartbeat(_hb(0.0, True, 3))
            arrivals: list[tuple[float, str]] = []  # (time at PX4, what)
            for k in range(40):  # frames every 50 ms; the first setpoint sent late, the rest early
                t = 1.0 + start_s + 0.05 * k  # the frame's time: what the stream is measured in
                sent = t + 0.06 + (jitter_s if k == 0 else -jitter_s)  # the camera's latency
                m.on_streamed(t)
                m.on_controller(True)
                arrivals.append((sent + 0.002, "sp"))
                arrivals += [(sent + 0.002 - cmd_ahead_s, "cmd") for a in m.step(t)
                             if a.kind == "set_mode"]
            results, tick = [], 0.0 + phase_s  # PX4's commander loop: checks, then commands
            for t_px4, what in sorted(arrivals):
                while tick < t_px4:
                    px4.update(tick, px4._state)
                    tick = round(tick + 0.01, 9)
                if what == "sp":
                    px4.on_attitude_target(t_px4, sp)
                else:
                    results.append(px4.handle_command(tick, 176, (1, 6, 0)).result)
            assert results[:1] == [ACCEPTED], (start_s, jitter_s, cmd_ahead_s, results)
            assert px4.mode is Mode.OFFBOARD


def test_a_stream_in_float_frame_times_is_not_judged_one_step_short() -> None:
    """Frame times are floats on the autopilot's clock: 37.55 - 37.40 is 0.1499999... s. A
    0.15 s escape stream from 37.40 s is requested at 37.55 s, not a step later."""
    cfg = OffboardConfig(preflight_stream_s=1.0, mode_retry_s=1.0, arm=False, exit_mode="hold",
                         preflight_escape_stream_s=0.15)
    m = OffboardManager(cfg)
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(37.0, True, 3))
    assert 37.55 - 37.40 < 0.15
    acts = _stream(m, 37.40, 37.80, escaping=True)
    assert acts == [(37.55, "set_mode")]
    m = OffboardManager(OffboardConfig(1.0, 1.0, False, "hold"))
    m.on_landed_state(IN_AIR)
    m.on_heartbeat(_hb(37.0, True, 3))
    assert _stream(m, 37.40, 38.60, escaping=False) == [(38.4, "set_mode")]
