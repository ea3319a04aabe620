"""Receipt time base: a backlog delivered after a stall keeps its true age (DelayFloor)."""

from __future__ import annotations

import pytest

from companion.control.timebase import DelayFloor, TimeBase


def test_steady_stream_has_no_excess_and_jitter_stays_small() -> None:
    fl = DelayFloor(stale_s=0.25)
    for i in range(200):
        t_src = 0.05 * i
        jitter = 0.004 * ((i * 7) % 5)
        assert fl.excess(1000.0 + t_src + 0.010 + jitter, t_src) <= 0.0161


def test_a_backlog_after_a_stall_is_late_then_fresh_items_are_not() -> None:
    fl = DelayFloor(stale_s=0.25)
    for i in range(100):  # 5 s at 20 Hz, 10 ms delay
        fl.excess(1000.0 + 0.05 * i + 0.01, 0.05 * i)
    # the process was stopped 2 s: 40 items captured during the stall arrive at once
    t_resume = 1000.0 + 5.0 + 2.0
    late = [fl.excess(t_resume, 5.0 + 0.05 * k) for k in range(40)]
    assert late[0] == pytest.approx(2.0 - 0.01, abs=0.01)
    assert all(x > 0.25 for x in late[:35])
    # then the stream is live again
    assert fl.excess(t_resume + 0.06, 7.05) == pytest.approx(0.0, abs=0.02)


def test_a_source_clock_jump_is_relearnt_after_3_s() -> None:
    fl = DelayFloor(stale_s=0.25, relearn_s=3.0)
    for i in range(40):
        fl.excess(100.0 + 0.05 * i, 0.05 * i)
    # the autopilot rebooted: its stamps restart at 0 while our clock runs on
    ex = [fl.excess(102.0 + 0.05 * i, 0.05 * i) for i in range(80)]
    assert ex[0] > 1.9 and ex[59] > 1.9  # late for 3 s ...
    assert max(ex[61:]) < 0.01           # ... then the new offset is learnt


def test_timebase_receipt_maps_stamped_messages_and_frames() -> None:
    tb = TimeBase("receipt", stale_s=0.25)
    for i in range(20):
        t = tb.message_s("ATTITUDE_QUATERNION", {"time_boot_ms": 50 * i}, int((10 + 0.05 * i
                                                                                 + 0.01) * 1e9))
        assert t == pytest.approx(10.01 + 0.05 * i, abs=1e-6)
    # a message received 2 s late keeps its source time (+ the stream's best delay)
    t = tb.message_s("ATTITUDE_QUATERNION", {"time_boot_ms": 1000}, int(13.01e9))
    assert t == pytest.approx(11.01, abs=5e-3)  # the floor may drift up 1 ms/s
    assert tb.last_excess_s == pytest.approx(2.0, abs=5e-3) and tb.stale_count == 1
    # unstamped: receipt time
    assert tb.message_s("HEARTBEAT", {}, int(13.5e9)) == pytest.approx(13.5)
    assert tb.frame_s(5_000_000, int(20e9)) == pytest.approx(20.0)  # first frame: the floor
    assert tb.frame_s(5_050_000, int(20.05e9)) == pytest.approx(20.05)
    tb.frame_s(5_100_000, int(22.1e9))
    assert tb.last_excess_s == pytest.approx(2.0, abs=5e-3)
