"""Lockstep (docs/reference/wire.md): simulated time advances one step per setpoint, or per
timeout."""

from __future__ import annotations

import socket
import time

from sim_bridge.config import with_link
from tests.sim.harness import MavClient, make_config, read_frame, run_sim


def _lockstep_cfg(client: MavClient, timeout_s: float, **changes: object):
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=timeout_s, **changes)
    return with_link(cfg, offboard_remote=f"127.0.0.1:{client.port}")


def _reply_each_step(client: MavClient, rs, q: list[float], thrust: float,
                     budget_s: float, until_ms: int | None = None) -> list[int]:
    """Answer every step (one ATTITUDE_QUATERNION per step) with one setpoint."""
    stamps: list[int] = []
    end = time.monotonic() + budget_s
    while time.monotonic() < end and rs.thread.is_alive():
        for m in client.recv(0.05):
            if m.get_type() == "ATTITUDE_QUATERNION":
                stamps.append(m.time_boot_ms)
                if until_ms is not None and m.time_boot_ms >= until_ms:
                    return stamps
                client.send(client.mav.set_attitude_target_encode(
                    m.time_boot_ms, 1, 1, 7, q, 0, 0, 0, thrust))
    return stamps


def test_one_step_per_setpoint(client: MavClient) -> None:
    """A client that answers every camera frame at once: 10 s of flight, one step per answer.
    (How much faster than real time is a figure for bench/lockstep.py, not a timed test.)"""
    cfg = _lockstep_cfg(client, timeout_s=2.0)
    q = [0.98078528, 0.0, 0.0, 0.19509032]  # level, yaw 22.5 deg: hover
    stamps: list[int] = []
    with run_sim(cfg, duration_s=10.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
        try:
            t0 = time.monotonic()
            cam.settimeout(0.5)
            while rs.thread.is_alive():
                try:
                    hdr, _ = read_frame(cam)
                except TimeoutError:
                    # step 0's frame left before we connected: release that step
                    assert not stamps
                    client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0,
                                                                      0.5))
                    cam.settimeout(5.0)
                    continue
                except ConnectionError:
                    break
                stamps.append(hdr["t_us"])
                client.send(client.mav.set_attitude_target_encode(
                    hdr["t_us"] // 1000, 1, 1, 7, q, 0, 0, 0, 0.5))
                client.drain()
            rs.thread.join(30.0)
            wall = time.monotonic() - t0
        finally:
            cam.close()
        stats = rs.stop()
    assert stats is not None
    assert stats.steps == 200 and abs(stats.t_s - 10.0) < 1e-9
    assert stats.lockstep_timeouts == 0
    # frames stamped with simulated time, one per 50 ms step, each answered once
    first = stamps[0] // 50_000
    assert first <= 1
    assert stamps == [50_000 * k for k in range(first, 200)]
    assert stats.setpoints_received == 200
    print(f"lockstep: 10 s of flight in {wall:.2f} s of wall time")


def test_time_advances_on_timeout_without_setpoints(client: MavClient) -> None:
    cfg = _lockstep_cfg(client, timeout_s=0.1)
    with run_sim(cfg, duration_s=100.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        time.sleep(1.0)
        st = rs.call(rs.sim.stats)
    # each step waited 0.1 s of wall time for a setpoint that never came
    assert 7 <= st.steps <= 11, st.steps
    assert st.lockstep_timeouts in (st.steps, st.steps + 1)
    assert abs(st.t_s - 0.05 * st.steps) < 1e-9


def test_offboard_loss_counts_simulated_time(client: MavClient) -> None:
    cfg = _lockstep_cfg(client, timeout_s=0.01)
    with run_sim(cfg, duration_s=100.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        q = [0.98078528, 0.0, 0.0, 0.19509032]  # level, yaw 22.5 deg
        _reply_each_step(client, rs, q, 0.5, budget_s=10.0, until_ms=1500)
        client.command(176, 1, 6, 0)
        ack = client.ack(176, 2.0)
        assert ack is not None and ack.result == 0
        stamps = _reply_each_step(client, rs, q, 0.5, budget_s=10.0, until_ms=3000)
        t_last_ms = stamps[-2]  # the last step we answered
        # silence: every step times out (0.01 s wall each); OFFBOARD ends 1.0 s SIM later
        fallback_ms = None
        status_after = None
        end = time.monotonic() + 10.0
        while fallback_ms is None and time.monotonic() < end:
            for m in client.recv(0.05):
                if m.get_type() == "HEARTBEAT" and m.custom_mode == 3 << 16:
                    fallback_ms = rs.call(lambda: int(rs.sim.t_s * 1000))
                    status_after = m.system_status
        assert fallback_ms is not None
        # PX4's HEARTBEAT.hpp: armed and a failsafe action in force -> MAV_STATE_CRITICAL (5)
        assert status_after == 5, status_after
        # PX4 falls back at t_last + COM_OF_LOSS_T (+ one step); the next 1 Hz heartbeat
        # reports it (sent at whole seconds of simulated time)
        assert t_last_ms + 1000 <= fallback_ms <= t_last_ms + 1000 + 1050, (t_last_ms,
                                                                            fallback_ms)
        events = rs.call(lambda: list(rs.sim.px4.events))
    lost = [e for e in events if "offboard lost" in e]
    assert len(lost) == 1
    t_lost = float(lost[0].split()[0])
    assert abs(t_lost - (t_last_ms / 1000 + 1.0 + 0.05)) < 0.051, (t_lost, t_last_ms)



def test_the_first_frame_waits_for_a_client_still_building_its_controller(
        client: MavClient) -> None:
    """sim.lockstep_start_timeout_s: the first frame a client got waits that long for its
    first answer (a companion compiling its controller for the vehicle's limits), every later
    one lockstep_timeout_s. The emulator's clock stands still meanwhile."""
    cfg = _lockstep_cfg(client, timeout_s=0.2, lockstep_start_timeout_s=30.0)
    q = [1.0, 0.0, 0.0, 0.0]
    with run_sim(cfg, duration_s=5.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=10.0)
        try:
            hdr, _ = read_frame(cam)  # the first frame this client gets
            time.sleep(2.0)  # "building": 10 ordinary timeouts long
            t_before = rs.call(lambda: rs.sim.t_s)
            timeouts_before = rs.call(lambda: rs.sim.stats().lockstep_timeouts)
            client.send(client.mav.set_attitude_target_encode(
                hdr["t_us"] // 1000, 1, 1, 7, q, 0, 0, 0, 0.5))
            hdr2, _ = read_frame(cam)
        finally:
            cam.close()
        rs.stop()
    assert t_before == hdr["t_us"] / 1e6  # the clock waited at the first frame's step
    assert hdr2["t_us"] == hdr["t_us"] + 50_000  # and went on with the answer
    # frames nobody got before the client connected waited the ordinary timeout only
    assert timeouts_before == hdr["t_us"] // 50_000
