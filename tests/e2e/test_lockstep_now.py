"""In lockstep the companion's "now" is the emulator's time, late only by what a real link costs.

``companion demo`` runs the companion with ``control.time_source = "autopilot"``: "now" is the
newest attitude or position stamp received. Over a realistic telemetry link (4 +- 2 ms transport
delay, PX4's onboard stream rates) and a camera with 60 +- 15 ms of latency (so that "now" is
not hidden behind the frame's own capture time, which the pipeline never lets "now" precede),
that "now", when the companion answers a frame, must be the emulator's simulated time at the
frame's delivery (where the lockstep step waits for the answer), late by at most the transport
delay plus one period of the attitude stream, as a real, continuously streaming
autopilot would leave it. It was one whole camera step (50 ms) late: the emulator sampled its
streams only at step boundaries, so the message stamped with a step's time arrived, through the
delay, only after that step's frame had been answered.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.reader import LogReader

pytestmark = pytest.mark.slow

DURATION_S = 3.0

# The realistic link (sim_bridge.config TELEMETRY_LEVELS["realistic"]): at most 4 + 2 ms of
# transport delay; PX4's onboard rates, where the fastest stream "now" is read from is
# ATTITUDE_QUATERNION at 50 Hz (the companion's attitude; LOCAL_POSITION_NED streams at 30 Hz);
# time_boot_ms counts whole milliseconds.
MAX_DELAY_S = 0.006
FASTEST_PERIOD_S = 0.020
STAMP_RESOLUTION_S = 0.001


def test_now_is_the_emulators_time_within_the_link_delay(tmp_path: Path) -> None:
    sim = tmp_path / "sim.toml"
    sim.write_text(f'base = "{DEFAULT_CONFIG}"\n[sim]\nlockstep_timeout_s = 10.0\n'
                   '[sim.telemetry]\nlevel = "realistic"\n'
                   '[sim.camera_model]\nlatency_ms = 60.0\nlatency_jitter_ms = 15.0\n')
    rep = run_demo(DEFAULT_CONFIG, "paper", DURATION_S, tmp_path, [], [], plots=False,
                   sim_config=sim)
    with LogReader(tmp_path / "flight.mcap") as r:
        truth = {m.data["frame_seq"]: m.data for m in r.messages(topics=["/truth"]) if m.data}
        steps = [m.data for m in r.messages(topics=["/control/step"]) if m.data]
    # one truth record per lockstep step, at the step's time (autopilot clock); a frame is
    # delivered at the first step at or after its delivery time, and the step then waits for
    # the answer: that step's time is the emulator's "now" while the companion answers
    step_us = sorted(rec["t_us"] for rec in truth.values())
    assert_every_delivery_answered(truth, step_us, steps, rep["steps"])
    lags = []
    for s in steps:
        rec = truth.get(s["frame_seq"])
        if rec is None or s.get("t_now_s") is None:
            continue
        due_us = rec["frame_deliver_t_us"]
        delivered_us = next((t for t in step_us if t >= due_us - 1), None)
        if delivered_us is not None:
            lags.append(delivered_us * 1e-6 - s["t_now_s"])
    assert len(lags) > 0.9 * len(steps), (len(lags), len(steps))
    assert min(lags) >= -1e-6, f"now ahead of the emulator by {-min(lags) * 1e3:.1f} ms"
    bound = MAX_DELAY_S + FASTEST_PERIOD_S + STAMP_RESOLUTION_S
    assert max(lags) <= bound, (
        f"now up to {max(lags) * 1e3:.1f} ms behind the emulator (bound {bound * 1e3:.0f} ms)")


def assert_every_delivery_answered(truth: dict, step_us: list[int], steps: list[dict],
                                   n_steps: int) -> None:
    """The flight ran: the newest frame of every lockstep step that delivered frames was
    answered. Latency jitter (60 +- 15 ms against 50 ms steps) delivers two frames in one step
    now and then, and the companion, reading the newest frame (``?frames=newest``), may skip the
    older one: a count of answered frames against all frames (52-57 of 60 in 3 s) is not a
    bound. Frames due after the run's end are not delivered; the first delivery may precede the
    companion's first step (it still builds on its first frame)."""
    newest: dict[int, int] = {}
    for seq, rec in truth.items():
        at = next((t for t in step_us if t >= rec["frame_deliver_t_us"] - 1), None)
        if at is not None:
            newest[at] = max(seq, newest.get(at, seq))
    answered = {s["frame_seq"] for s in steps}
    missed = sorted(seq for at, seq in newest.items() if seq not in answered)
    assert n_steps == len(steps)
    assert len(newest) > 0.8 * DURATION_S * 20, len(newest)
    assert missed in ([], [min(newest.values())]), (
        f"newest frame of a delivery step unanswered: {missed} of {len(newest)}")
