"""TIMESYNC (companion/control/timesync.py): the autopilot's clock on the companion's, against
synthetic clocks and against the emulator's PX4-like TIMESYNC over real UDP."""

from __future__ import annotations

import time

import pytest

from companion.control.timesync import TimeSync
from sim_bridge.config import TelemetryConfig
from tests.sim.harness import MavClient, sim_with_client

OFFSET_NS = 37_250_000_000 - 1_000_000_000  # autopilot minus local


def test_offset_from_the_smallest_round_trip() -> None:
    ts = TimeSync(window=5)
    # symmetric 1 ms link: exact; a queued reply (30 ms back, asymmetric) must not win
    for t0, up, down in [(0, 1_000_000, 1_000_000), (100_000_000, 1_000_000, 30_000_000),
                         (200_000_000, 4_000_000, 4_000_000)]:
        tc1, ts1 = ts.request(t0)
        assert tc1 == 0
        tc1_reply = t0 + up + OFFSET_NS
        assert ts.on_timesync(tc1_reply, ts1, t0 + up + down) is None
    best = ts.best
    assert best is not None and best.rtt_ns == 2_000_000
    now = ts.autopilot_s(5_000_000_000)
    assert now == pytest.approx((5_000_000_000 + OFFSET_NS) * 1e-9, abs=1e-9)


def test_requests_from_the_autopilot_are_answered_and_strangers_ignored() -> None:
    ts = TimeSync()
    assert ts.on_timesync(0, 123, 456) == (456, 123)  # PX4's request: our time, ts1 echoed
    assert ts.on_timesync(999, 77, 1000) is None  # a reply to a request we never sent
    assert ts.rejected == 1 and ts.best is None and ts.autopilot_s(0) is None
    _, ts1 = ts.request(1_000)
    assert ts.on_timesync(5_000, ts1, 1_000 + 10**9) is None  # 1 s round trip: rejected
    assert ts.rejected == 2 and ts.best is None


def test_maps_the_emulators_clock_over_udp() -> None:
    """Realtime emulator whose autopilot booted 37.25 s before: the mapped local clock agrees
    with the next ATTITUDE_QUATERNION's time_boot_ms within a stream period."""
    c = MavClient()
    try:
        with sim_with_client(c, telemetry=TelemetryConfig(boot_offset_s=37.25)):
            ts = TimeSync()
            assert c.wait_for(lambda m: m.get_type() == "HEARTBEAT", 2.0) is not None
            for _ in range(5):
                c.send(c.mav.timesync_encode(*ts.request(time.monotonic_ns())))
                m = c.wait_for(lambda m: m.get_type() == "TIMESYNC" and m.tc1 != 0, 1.0)
                assert m is not None
                ts.on_timesync(m.tc1, m.ts1, time.monotonic_ns())
            c.drain()
            aq = c.wait_for(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 1.0)
            mapped = ts.autopilot_s(time.monotonic_ns())
    finally:
        c.close()
    assert aq is not None and mapped is not None
    # the sample was taken when the message was generated (<= one 20 ms period ago), plus
    # scheduling on a loaded machine
    assert 0.0 <= mapped - aq.time_boot_ms * 1e-3 < 0.1
    assert mapped > 37.25
