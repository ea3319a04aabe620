"""The actuation delay measured online from TIMESYNC probes (companion/control/timesync.py
ActuationDelayMeter, ``control.latency.auto_delay``): real pymavlink TIMESYNC messages, and
the emulator's PX4-like answer through its network impairment over real UDP."""

from __future__ import annotations

import random
import statistics
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion import ConfigError
from companion.config import load_config
from companion.control.timesync import ActuationDelayMeter
from sim_bridge.config import ImpairmentConfig, TelemetryConfig
from sim_bridge.impairment import ImpairmentParams
from tests.sim.harness import MavClient, sim_with_client

NS = 1_000_000_000


def _wire(tc1: int, ts1: int) -> Any:
    """A TIMESYNC as PX4 sends it, through pymavlink's packer and a fresh parser."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = mav.timesync_encode(tc1, ts1).pack(mav)
    (msg,) = mavlink2.MAVLink(None).parse_buffer(buf)
    assert msg.get_type() == "TIMESYNC"
    return msg


def test_autopilot_clock_median_of_the_round_trip() -> None:
    """time_source "autopilot": now is the newest telemetry stamp; PX4 stamps the probe's
    arrival (tc1) on the same clock, so a sample is the vehicle -> companion delay plus the
    companion -> vehicle delay. 20 + U(0, 60) ms each way: the median of the window is the
    median round trip, a late reply does not move it, and nothing is used before 5 samples."""
    rng = random.Random(3)
    m = ActuationDelayMeter("autopilot", window=41, min_samples=5, max_s=0.5,
                            probe_interval_s=0.0)
    rtts = []
    for k in range(60):
        t_state = 20.0 + 0.05 * k  # the vehicle's clock when the newest telemetry was sampled
        up, down = 0.02 + rng.uniform(0, 0.06), 0.02 + rng.uniform(0, 0.06)
        now = t_state  # "autopilot": the step's now is that stamp (received `up` later)
        ts1 = 5 * NS + k * 50_000_000  # local ns at sending (any unique value)
        m.sent(ts1, now)
        rtt = 0.3 if k == 30 else up + down  # one reply queued behind a stall
        rtts.append(rtt)
        msg = _wire(round((now + rtt) * NS), ts1)
        assert m.on_reply(msg.tc1, msg.ts1, 0) == pytest.approx(rtt, abs=1e-6)
        if k < 4:
            assert m.value() is None  # the configured constant is used meanwhile
        else:  # asked every step (cached between replies): always the window's median
            window = [max(r, 0.0) for r in rtts[-41:]]
            assert m.value() == pytest.approx(statistics.median(window), abs=1e-6)
            assert m.value() == m.value()
    v = m.value()
    assert v is not None and m.samples == 41
    assert v == pytest.approx(statistics.median(rtts[-41:]), abs=1e-6)
    assert 0.08 < v < 0.12  # 2 x (20 + 30) ms, not the 0.3 s outlier
    assert m.spread() is not None and m.spread() > 0.2  # type: ignore[operator]


def test_strangers_duplicates_and_out_of_bounds_replies_are_ignored() -> None:
    m = ActuationDelayMeter("autopilot", window=5, min_samples=1, max_s=0.5)
    m.sent(111, 10.0)
    req = _wire(0, 111)  # the autopilot's own request (tc1 = 0): not an answer
    assert m.on_reply(req.tc1, req.ts1, 0) is None
    strange = _wire(10_050_000_000, 999)  # answers a request we never sent
    assert m.on_reply(strange.tc1, strange.ts1, 0) is None
    ok = _wire(10_050_000_000, 111)
    assert m.on_reply(ok.tc1, ok.ts1, 0) == pytest.approx(0.05)
    assert m.on_reply(ok.tc1, ok.ts1, 0) is None  # a duplicated datagram
    m.sent(222, 11.0)
    late = _wire(11_800_000_000, 222)  # 0.8 s: above max_s
    assert m.on_reply(late.tc1, late.ts1, 0) is None
    m.sent(333, 12.0)
    early = _wire(11_900_000_000, 333)  # arrived before "now": another clock, not a delay
    assert m.on_reply(early.tc1, early.ts1, 0) is None
    assert m.rejected == 2 and m.samples == 1 and m.value() == pytest.approx(0.05)


def test_receipt_clock_uses_the_replys_arrival() -> None:
    """time_source "receipt": the state the setpoint acts on is seen a vehicle -> companion
    delay after the vehicle acts, like the reply: the sample is the local round trip, whatever
    the autopilot's clock reads."""
    m = ActuationDelayMeter("receipt", window=3, min_samples=3, max_s=0.5,
                            probe_interval_s=0.0)
    for k, rtt_ms in enumerate((90, 110, 100)):
        now = 100.0 + k
        ts1 = round(now * NS)
        m.sent(ts1, now)
        msg = _wire(7 * NS, ts1)  # the autopilot's clock: unrelated to ours
        m.on_reply(msg.tc1, msg.ts1, ts1 + rtt_ms * 1_000_000)
    assert m.value() == pytest.approx(0.100)


def test_probe_rate() -> None:
    m = ActuationDelayMeter("timesync", probe_interval_s=0.1)
    assert m.due(5.0)
    m.sent(1, 5.0)
    assert not m.due(5.05) and m.due(5.1)
    assert m.due(1.0)  # the time base went back (a new flight): probe again


def test_config() -> None:
    lat = load_config().control.latency
    assert lat.auto_delay and lat.actuation_delay_s == 0.0
    for bad in ("auto_delay_window=0", "auto_delay_min_samples=30", "auto_delay_max_s=0",
                "auto_delay_probe_hz=0", "auto_delay_max_s=1.5"):
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            load_config(overrides=[f"control.latency.{bad}"])
    with pytest.raises(ConfigError, match="auto_delay"):
        load_config(overrides=['control.latency.auto_delay="yes"'])


@pytest.mark.parametrize("delay_s", [0.0, 0.05])
def test_the_emulators_impairment_delays_the_probe(delay_s: float) -> None:
    """Realtime emulator (autopilot booted 37.25 s earlier) whose offboard link delays every
    datagram ``delay_s`` each way: probes stamped with the newest ATTITUDE_QUATERNION's
    time_boot_ms measure the round trip plus the telemetry's age (a 50 Hz stream)."""
    imp = ImpairmentConfig(vehicle_to_companion=ImpairmentParams(delay_s=delay_s),
                           companion_to_vehicle=ImpairmentParams(delay_s=delay_s))
    m = ActuationDelayMeter("autopilot", window=9, min_samples=5, probe_interval_s=0.0)
    c = MavClient()
    try:
        with sim_with_client(c, telemetry=TelemetryConfig(boot_offset_s=37.25),
                             impairment=imp):
            aq = c.wait_for(lambda x: x.get_type() == "ATTITUDE_QUATERNION", 2.0)
            assert aq is not None
            for k in range(9):
                c.drain()
                aq = c.wait_for(lambda x: x.get_type() == "ATTITUDE_QUATERNION", 1.0)
                assert aq is not None
                ts1 = 1_000 + k
                m.sent(ts1, aq.time_boot_ms * 1e-3)
                c.send(c.mav.timesync_encode(0, ts1))
                r = c.wait_for(lambda x, ts1=ts1: x.get_type() == "TIMESYNC" and x.tc1 != 0
                               and x.ts1 == ts1, 2.0)
                assert r is not None
                m.on_reply(r.tc1, r.ts1, 0)
    finally:
        c.close()
    v = m.value()
    assert v is not None and m.rejected == 0
    assert 2 * delay_s <= v < 2 * delay_s + 0.06, v
