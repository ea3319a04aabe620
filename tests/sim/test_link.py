"""The emulator's MAVLink behaviour over real UDP sockets on 127.0.0.1 (pymavlink client)."""

from __future__ import annotations

import math
import time

from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge.link import MAX_PEERS, PEER_TIMEOUT_S, MavUdpLink
from sim_bridge.physics.vehicle import euler_from_quat, quat_from_euler
from tests.sim.harness import MavClient, make_config, sim_with_client

ARM = 400
SET_MODE = 176
REQUEST_MESSAGE = 512
SET_MESSAGE_INTERVAL = 511
OFFBOARD_CUSTOM = 6 << 16
POSCTL_CUSTOM = 3 << 16


def _hb(c: MavClient, timeout_s: float = 2.0):
    return c.wait_for(lambda m: m.get_type() == "HEARTBEAT", timeout_s)


def _stream(c: MavClient, seconds: float, roll_rad: float = 0.0, yaw_rad: float = 0.0,
            thrust: float = 0.5, mask: int = 7, rate_hz: float = 20.0) -> None:
    q = quat_from_euler(roll_rad, 0.0, yaw_rad)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        c.send(c.mav.set_attitude_target_encode(0, 1, 1, mask, [float(v) for v in q], 0.0, 0.0,
                                                0.0, thrust))
        c.drain()
        time.sleep(1.0 / rate_hz)


def _fast_heartbeat(c: MavClient) -> None:
    c.command(SET_MESSAGE_INTERVAL, 0, 20_000)  # HEARTBEAT every 20 ms
    ack = c.ack(SET_MESSAGE_INTERVAL)
    assert ack is not None and ack.result == 0


def test_heartbeat_encoding_and_streams(client: MavClient) -> None:
    with sim_with_client(client):
        msgs = client.collect(1.2)
    kinds = [m.get_type() for m in msgs]
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert 1 <= len(hb) <= 2  # 1 Hz
    h = hb[0]
    assert (h.get_srcSystem(), h.get_srcComponent()) == (1, 1)
    assert (h.type, h.autopilot) == (2, 12)
    assert h.base_mode == 1 | 16 | 64 | 128  # armed in POSCTL (airborne start)
    assert h.custom_mode == POSCTL_CUSTOM
    n_att = kinds.count("ATTITUDE_QUATERNION")
    assert 40 <= n_att <= 70, n_att  # ~50 Hz over 1.2 s
    assert 25 <= kinds.count("LOCAL_POSITION_NED") <= 45
    for needed in ("ATTITUDE", "EXTENDED_SYS_STATE", "SYS_STATUS"):
        assert needed in kinds
    aq = next(m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION")
    _, _, yaw = euler_from_quat([aq.q1, aq.q2, aq.q3, aq.q4])
    assert math.isclose(yaw, 0.39269908169872414, abs_tol=1e-4)  # the paper scenario's pose
    lp = next(m for m in msgs if m.get_type() == "LOCAL_POSITION_NED")
    assert math.isclose(lp.z, -3.2, abs_tol=0.01)
    es = next(m for m in msgs if m.get_type() == "EXTENDED_SYS_STATE")
    assert es.landed_state == 2  # in air


def test_mavsdk_connect_time_requests_are_answered(client: MavClient) -> None:
    with sim_with_client(client):
        client.command(REQUEST_MESSAGE, 148)
        got = client.collect(0.5)
        acks = [m for m in got if m.get_type() == "COMMAND_ACK"]
        assert [(a.command, a.result) for a in acks] == [(REQUEST_MESSAGE, 0)]
        assert (acks[0].target_system, acks[0].target_component) == (1, 191)
        assert any(m.get_type() == "AUTOPILOT_VERSION" for m in got)
        client.command(REQUEST_MESSAGE, 242)
        home = client.wait_for(lambda m: m.get_type() == "HOME_POSITION", 1.0)
        assert home is not None and math.isclose(home.z, -3.2, abs_tol=1e-6)
        client.command(REQUEST_MESSAGE, 99999)  # nothing we could send
        ack = client.ack(REQUEST_MESSAGE)
        assert ack is not None and ack.result == 2  # DENIED
        client.send(client.mav.ping_encode(123456, 7, 0, 0))
        pong = client.wait_for(lambda m: m.get_type() == "PING", 1.0)
        assert pong is not None and (pong.time_usec, pong.seq) == (123456, 7)
        assert (pong.target_system, pong.target_component) == (1, 191)


def test_set_message_interval_changes_rate(client: MavClient) -> None:
    with sim_with_client(client):
        _fast_heartbeat(client)
        n = sum(m.get_type() == "HEARTBEAT" for m in client.collect(0.5))
        assert n >= 15  # 50 Hz now
        client.command(SET_MESSAGE_INTERVAL, 31, -1)  # ATTITUDE_QUATERNION off
        assert client.ack(SET_MESSAGE_INTERVAL).result == 0
        time.sleep(0.05)
        client.drain()
        assert not any(m.get_type() == "ATTITUDE_QUATERNION" for m in client.collect(0.3))


def test_mode_switch_and_arming_rejections(client: MavClient) -> None:
    with sim_with_client(client, start="ground"):
        h = _hb(client)
        assert h.base_mode & 128 == 0 and h.custom_mode == POSCTL_CUSTOM
        # disarmed: OFFBOARD is accepted without a signal ...
        client.command(SET_MODE, 1, 6, 0)
        assert client.ack(SET_MODE).result == 0
        # ... but arming in OFFBOARD without the signal is rejected
        client.command(ARM, 1)
        assert client.ack(ARM).result == 1  # TEMPORARILY_REJECTED
        _fast_heartbeat(client)
        h = _hb(client)
        assert h.custom_mode == OFFBOARD_CUSTOM and h.base_mode & 128 == 0
        # with a fresh signal it arms
        _stream(client, 1.0, thrust=0.2)
        client.command(ARM, 1)
        assert client.ack(ARM).result == 0
        h = client.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.base_mode & 128, 1.0)
        assert h is not None and h.base_mode == 128 | 16 | 1  # 145: armed in OFFBOARD
        # param1 neither 0 nor 1: unsupported
        client.command(ARM, 0.3 + 5)
        assert client.ack(ARM).result == 3
        # unknown command: UNSUPPORTED
        client.command(31337)
        assert client.ack(31337).result == 3


def test_armed_offboard_without_signal_is_temporarily_rejected(client: MavClient) -> None:
    with sim_with_client(client):  # airborne: armed in POSCTL
        client.command(SET_MODE, 1, 6, 0)
        assert client.ack(SET_MODE).result == 1
        client.command(ARM, 0)  # disarm in the air: rejected
        assert client.ack(ARM).result == 1
        _fast_heartbeat(client)
        h = _hb(client)
        assert h.custom_mode == POSCTL_CUSTOM and h.base_mode & 128


def test_offboard_loss_falls_back_to_position_in_time(client: MavClient) -> None:
    with sim_with_client(client):
        _fast_heartbeat(client)
        _stream(client, 1.0)
        client.command(SET_MODE, 1, 6, 0)
        assert client.ack(SET_MODE).result == 0
        _stream(client, 0.5)
        client.send(client.mav.set_attitude_target_encode(
            0, 1, 1, 7, [float(v) for v in quat_from_euler(0, 0, 0.39)], 0, 0, 0, 0.5))
        t_last = time.monotonic()
        seen_offboard = False
        t_pos = None
        while time.monotonic() - t_last < 2.0:
            for m in client.recv(0.1):
                if m.get_type() != "HEARTBEAT":
                    continue
                if m.custom_mode == OFFBOARD_CUSTOM:
                    seen_offboard = True
                elif m.custom_mode == POSCTL_CUSTOM and t_pos is None:
                    t_pos = time.monotonic()
            if t_pos is not None:
                break
        assert seen_offboard
        assert t_pos is not None, "never fell back to Position"
        delay = t_pos - t_last
        assert 0.9 <= delay <= 1.0 + 0.1, delay  # COM_OF_LOSS_T = 1.0 s


def test_throttle_ignore_is_neither_a_signal_nor_applied(client: MavClient) -> None:
    with sim_with_client(client):
        _fast_heartbeat(client)
        # bit 64 only: no signal, so OFFBOARD is refused while armed
        _stream(client, 1.0, roll_rad=0.3, mask=7 | 64)
        client.command(SET_MODE, 1, 6, 0)
        assert client.ack(SET_MODE).result == 1
        # a real signal, then OFFBOARD, holding level
        _stream(client, 1.0, yaw_rad=0.39269908169872414)
        client.command(SET_MODE, 1, 6, 0)
        assert client.ack(SET_MODE).result == 0
        _stream(client, 0.3, yaw_rad=0.39269908169872414)
        # now only THROTTLE_IGNORE setpoints asking for 0.3 rad roll: not applied ...
        t0 = time.monotonic()
        max_roll = 0.0
        fell_back = None
        q = [float(v) for v in quat_from_euler(0.3, 0.0, 0.39269908169872414)]
        while time.monotonic() - t0 < 1.6:
            client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7 | 64, q, 0, 0, 0, 0.5))
            for m in client.recv(0.05):
                if m.get_type() == "ATTITUDE":
                    max_roll = max(max_roll, abs(m.roll))
                if m.get_type() == "HEARTBEAT" and m.custom_mode == POSCTL_CUSTOM and (
                        fell_back is None):
                    fell_back = time.monotonic() - t0
        assert max_roll < 0.02, max_roll
        # ... and not a signal: offboard is lost after COM_OF_LOSS_T
        assert fell_back is not None and 0.8 <= fell_back <= 1.2, fell_back


def test_commands_for_other_systems_get_no_ack_and_each_command_one_ack(
        client: MavClient) -> None:
    with sim_with_client(client):
        client.drain()
        for target in ((2, 1), (1, 2), (42, 0)):
            client.command(SET_MESSAGE_INTERVAL, 30, 100_000, target=target)
        assert client.ack(SET_MESSAGE_INTERVAL, 0.7) is None
        n = 25
        for i in range(n):
            client.command(31000 + i, target=(1, 1) if i % 2 else (0, 0))
        acks = [m for m in client.collect(1.0) if m.get_type() == "COMMAND_ACK"]
        assert sorted(a.command for a in acks) == [31000 + i for i in range(n)]
        assert all(a.result == 3 for a in acks)
        # the same command sent twice (a retry) is answered twice, once each
        client.command(SET_MESSAGE_INTERVAL, 30, 100_000)
        client.command(SET_MESSAGE_INTERVAL, 30, 100_000)
        acks = [m for m in client.collect(0.7) if m.get_type() == "COMMAND_ACK"]
        assert len(acks) == 2


def test_second_client_gets_its_own_ack(client: MavClient) -> None:
    other = MavClient(sysid=245, compid=190)
    try:
        with sim_with_client(client) as rs:
            other.target = ("127.0.0.1", rs.ports["offboard"])
            other.command(ARM, 1)
            ack = other.ack(ARM)
            assert ack is not None and ack.result == 0
            assert (ack.target_system, ack.target_component) == (245, 190)
            # and it now gets telemetry too (PX4 answers whoever talks to it)
            assert other.wait_for(lambda m: m.get_type() == "HEARTBEAT", 2.0) is not None
    finally:
        other.close()


def test_mavlink1_frames_are_dropped(client: MavClient) -> None:
    with sim_with_client(client) as rs:
        mav1 = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        msg = mav1.command_long_encode(1, 1, 31999, 0, 0, 0, 0, 0, 0, 0, 0)
        client.send_raw(msg.pack(mav1, force_mavlink1=True))
        assert client.ack(31999, 0.5) is None
        c = rs.call(lambda: rs.sim.links["offboard"].counters)
        assert c.rx_mavlink1 == 1


def test_peers_are_bounded_and_expire() -> None:
    now = [0.0]
    link = MavUdpLink("t", "127.0.0.1", 0, ("127.0.0.1", 9), 1, 1, clock=lambda: now[0])
    gcs = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    hb = gcs.heartbeat_encode(6, 8, 0, 0, 0, 3).pack(gcs)
    for port in range(20000, 20100):
        link._on_datagram(hb, ("127.0.0.1", port))
        now[0] += 0.01
    assert len(link._peers) <= MAX_PEERS
    assert ("127.0.0.1", 20099) in link.peers and link.peers[0] == ("127.0.0.1", 9)
    now[0] += PEER_TIMEOUT_S + 1
    assert link.peers == [("127.0.0.1", 9)]
    assert link.counters.rx_messages == 100


def test_attitude_target_reports_the_thrust_px4_flies(client: MavClient) -> None:
    """PX4 streams ATTITUDE_TARGET (10 Hz on an onboard link): before OFFBOARD its thrust is
    the one PX4's own mode flies, i.e. the vehicle's true hover thrust (MPC_USE_HTE), not the
    configured MPC_THR_HOVER; in OFFBOARD it is the companion's setpoint."""
    import dataclasses

    vehicle = dataclasses.replace(make_config().sim.vehicle, true_hover_thrust=0.62)
    with sim_with_client(client, vehicle=vehicle):
        msgs = client.collect(1.2)
        at = [m for m in msgs if m.get_type() == "ATTITUDE_TARGET"]
        assert 5 <= len(at) <= 16, len(at)  # ~10 Hz
        assert all(math.isclose(m.thrust, 0.62, abs_tol=0.01) for m in at[2:]), \
            [m.thrust for m in at]
        _stream(client, 0.3, thrust=0.44)
        client.command(SET_MODE, 1, 6)
        _stream(client, 0.5, thrust=0.44)
        got = client.collect(0.3)
        at = [m for m in got if m.get_type() == "ATTITUDE_TARGET"]
        assert at and all(math.isclose(m.thrust, 0.44, abs_tol=1e-6) for m in at)
