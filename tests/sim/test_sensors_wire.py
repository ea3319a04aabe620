"""The imperfect camera and telemetry on the wire (docs/reference/wire.md, Clocks): frames arrive
late by the configured latency stamped with their capture time, drops leave seq gaps, the
autopilot's
clock starts at its boot offset, TIMESYNC is answered (and asked) like PX4."""

from __future__ import annotations

import dataclasses
import itertools
import select
import socket
import time
from collections.abc import Iterator
from typing import Any

from sim_bridge.config import CameraModelConfig, TelemetryConfig, with_link
from tests.sim.harness import MavClient, make_config, read_frame, run_sim, sim_with_client

BOOT_OFFSET_S = 37.25
STEP_US = 50_000


def _step_batches(rs: Any) -> Iterator[list[dict[str, Any]]]:
    """The frame headers of each lockstep step, as the camera socket delivers them (a step can
    deliver two: every frame waiting after the first), until the emulator stops."""
    cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
    try:
        cam.settimeout(5.0)
        while rs.thread.is_alive():
            try:
                batch = [read_frame(cam)[0]]
                while select.select([cam], [], [], 0.03)[0]:
                    batch.append(read_frame(cam)[0])
            except (TimeoutError, ConnectionError):
                return
            yield batch
    finally:
        cam.close()


def test_lockstep_frames_arrive_late_by_the_latency_with_capture_stamps(
        client: MavClient) -> None:
    """Lockstep, latency 60 +- 15 ms, 20 % drops: each frame is delivered at the first step at
    or after its capture + latency (45..75 ms: 50 ms later when the drawn latency is <= 50 ms,
    1/6 of the frames, else 100 ms) and stamped with its capture time on the autopilot clock
    (simulation time + boot offset)."""
    cm = CameraModelConfig(latency_ms=60.0, latency_jitter_ms=15.0, drop_probability=0.2)
    tm = TelemetryConfig(boot_offset_s=BOOT_OFFSET_S)
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=2.0, camera_model=cm,
                      telemetry=tm)
    cfg = with_link(cfg, offboard_remote=f"127.0.0.1:{client.port}")
    q = [0.98078528, 0.0, 0.0, 0.19509032]
    got: list[tuple[int, int, int]] = []  # (seq, stamp_us, delivery step time_boot_us)
    latest_ms = 0
    with run_sim(cfg, duration_s=10.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        for batch in _step_batches(rs):
            # the emulator is blocked in this step: all its telemetry is here
            for m in client.collect(0.01):
                if m.get_type() == "ATTITUDE_QUATERNION":
                    latest_ms = max(latest_ms, m.time_boot_ms)
            got += [(h["seq"], h["t_us"], latest_ms * 1000) for h in batch]
            for _ in batch:  # one answer per frame (docs/reference/wire.md, lockstep)
                client.send(client.mav.set_attitude_target_encode(
                    latest_ms, 1, 1, 7, q, 0, 0, 0, 0.5))
        stats = rs.stop()
    assert stats is not None
    assert len(got) > 100
    offset_us = round(BOOT_OFFSET_S * 1e6)
    late = []
    for seq, stamp, deliver in got[1:]:
        # capture stamps on the step grid of the autopilot clock, seq k captured at step k
        assert stamp == offset_us + seq * STEP_US
        late.append(deliver - stamp)
    # first step >= capture + 45..75 ms
    assert set(late) <= {50_000, 100_000}, set(late)
    share_100 = late.count(100_000) / len(late)
    assert 0.7 < share_100 < 0.95, share_100  # 5/6 expected
    seqs = [g[0] for g in got]
    assert seqs == sorted(seqs)
    gaps = sum(b - a - 1 for a, b in itertools.pairwise(seqs))
    assert gaps <= stats.frames_dropped
    n = stats.frames
    assert 0.2 * n - 4 * (0.16 * n) ** 0.5 < stats.frames_dropped < 0.2 * n + 4 * (0.16 * n) ** 0.5
    assert stats.lockstep_timeouts <= 1
    assert stats.steps == 200


def test_time_boot_ms_timesync_and_frames_share_the_autopilot_clock(client: MavClient) -> None:
    """Realtime, boot offset 37.25 s, PX4 rates: time_boot_ms starts near 37250; a TIMESYNC
    request gets tc1 = autopilot time in ns and ts1 echoed; frame stamps are on that clock; the
    autopilot sends its own TIMESYNC requests (10 Hz) and uses our answers."""
    tm = TelemetryConfig(rates="px4", boot_offset_s=BOOT_OFFSET_S)
    with sim_with_client(client, telemetry=tm) as rs:
        cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
        try:
            aq = client.wait_for(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 2.0)
            assert aq is not None
            assert 37_250 <= aq.time_boot_ms < 37_250 + 3_000
            client.drain()
            client.send(client.mav.timesync_encode(0, 123_456_789))
            rep = client.wait_for(lambda m: m.get_type() == "TIMESYNC" and m.tc1 != 0, 2.0)
            after = client.wait_for(lambda m: m.get_type() == "ATTITUDE_QUATERNION", 1.0)
            assert rep is not None and after is not None
            assert rep.ts1 == 123_456_789
            assert (rep.get_srcSystem(), rep.get_srcComponent()) == (1, 1)
            # tc1 in ns on the same clock as time_boot_ms (within the 20 ms stream period)
            assert abs(rep.tc1 / 1e6 - after.time_boot_ms) < 40
            hdr, _ = read_frame(cam)
            assert abs(hdr["t_us"] / 1000 - after.time_boot_ms) < 1_000
            assert hdr["t_us"] >= round(BOOT_OFFSET_S * 1e6)
            # PX4's own request: tc1 = 0, ts1 = its boot time in ns; answer it like a companion
            req = client.wait_for(lambda m: m.get_type() == "TIMESYNC" and m.tc1 == 0, 1.0)
            assert req is not None
            assert abs(req.ts1 / 1e6 - after.time_boot_ms) < 2_000
            my_clock_ns = 5_000_000_000
            client.send(client.mav.timesync_encode(my_clock_ns, req.ts1))
            time.sleep(0.2)
            st = rs.call(rs.sim.stats)
        finally:
            cam.close()
    assert st.timesync_replies == 1
    assert st.timesync_rtt_us is not None and 0 <= st.timesync_rtt_us < 200_000
    # PX4's offset sample (ts1 + now - 2 tc1) / 2 ~ autopilot time - our clock
    assert st.timesync_offset_us is not None
    assert abs(st.timesync_offset_us - (req.ts1 / 1e3 - my_clock_ns / 1e3)) < 200_000


def test_px4_onboard_stream_rates(client: MavClient) -> None:
    tm = TelemetryConfig(rates="px4")
    with sim_with_client(client, telemetry=tm):
        client.wait_for(lambda m: m.get_type() == "HEARTBEAT", 2.0)
        msgs = client.collect(2.0)
    kinds = [m.get_type() for m in msgs]
    per_s = {k: kinds.count(k) / 2.0 for k in set(kinds)}
    assert 8 <= per_s.get("TIMESYNC", 0) <= 11, per_s  # ~10 Hz (we sent no request)
    assert 35 <= per_s.get("ATTITUDE_QUATERNION", 0) <= 55, per_s
    assert 20 <= per_s.get("LOCAL_POSITION_NED", 0) <= 33, per_s
    assert 50 <= per_s.get("ATTITUDE", 0) <= 101, per_s  # 100 Hz, the loop ticks every 10 ms
    assert 0.5 <= per_s.get("SYSTEM_TIME", 0) <= 1.5, per_s
    assert 3 <= per_s.get("SYS_STATUS", 0) <= 6, per_s


def test_transport_delay_in_realtime(client: MavClient) -> None:
    """200 ms transport delay: a TIMESYNC round trip takes ~200 ms, and its tc1 is the time
    the request arrived (PX4 stamps on receipt)."""
    tm = TelemetryConfig(delay_ms=200.0, delay_jitter_ms=0.0)
    with sim_with_client(client, telemetry=tm):
        assert client.wait_for(lambda m: m.get_type() == "HEARTBEAT", 3.0) is not None
        rtts = []
        for i in range(3):
            client.drain()
            t0 = time.monotonic()
            client.send(client.mav.timesync_encode(0, 1000 + i))
            rep = client.wait_for(lambda m, i=i: m.get_type() == "TIMESYNC"
                                  and m.ts1 == 1000 + i, 2.0)
            assert rep is not None
            rtts.append(time.monotonic() - t0)
    assert all(0.19 <= r <= 0.3 for r in rtts), rtts


def test_ideal_levels_change_nothing() -> None:
    cfg = make_config()
    assert cfg.sim.camera_model == CameraModelConfig()
    assert cfg.sim.telemetry == TelemetryConfig()
    assert dataclasses.asdict(cfg.sim.camera_model)["level"] == "ideal"


def test_lockstep_answer_to_the_newest_frame_releases_a_step_of_two(client: MavClient) -> None:
    """Lockstep, latency 60 +- 15 ms: some steps deliver two frames. A client that reads only
    the newest frame (the companion's ``?frames=newest``) answers it alone, stamped with its
    capture time: that answer releases the step (no lockstep timeout), where counting answers
    would wait out the timeout for the skipped frame."""
    cm = CameraModelConfig(latency_ms=60.0, latency_jitter_ms=15.0)
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=1.0, camera_model=cm,
                      telemetry=TelemetryConfig(boot_offset_s=BOOT_OFFSET_S))
    cfg = with_link(cfg, offboard_remote=f"127.0.0.1:{client.port}")
    q = [1.0, 0.0, 0.0, 0.0]
    batches: list[int] = []
    with run_sim(cfg, duration_s=6.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        for batch in _step_batches(rs):
            batches.append(len(batch))
            newest_ms = batch[-1]["t_us"] // 1000
            client.send(client.mav.set_attitude_target_encode(
                newest_ms, 1, 1, 7, q, 0, 0, 0, 0.5))
        stats = rs.stop()
    assert stats is not None
    assert batches.count(2) >= 5, batches  # steps that delivered two frames (~5/36 of them)
    assert stats.lockstep_timeouts <= 1  # the first step, before the client connected
    assert stats.steps == 120
