"""Network impairment (sim_bridge.impairment): the pure core against binomial bounds and
ordering rules, then the emulator's links over real loopback UDP with a pymavlink client."""

from __future__ import annotations

import itertools
import math
import socket
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge import ConfigError
from sim_bridge.config import ImpairmentConfig, load_config, with_link
from sim_bridge.impairment import (
    DirectionImpairment,
    ImpairmentParams,
    LinkImpairment,
    flip_bits,
    msgid_of,
)
from tests.sim.harness import MavClient, make_config, read_frame, run_sim, sim_with_client

N = 20_000


def _frame(msgid_payload: int = 0, seq: int = 0) -> bytes:
    """A real MAVLink 2 frame (HEARTBEAT if ``msgid_payload`` is 0, else a SYSTEM_TIME)."""
    out: list[bytes] = []

    class W:
        def write(self, b: bytes) -> None:
            out.append(bytes(b))

    mav = mavlink2.MAVLink(W(), srcSystem=1, srcComponent=1)
    mav.seq = seq & 0xFF
    if msgid_payload == 0:
        mav.send(mav.heartbeat_encode(2, 12, 0, 0, 3, 3))
    else:
        mav.send(mav.system_time_encode(seq, seq))
    return out[0]


def _binomial_ok(k: int, n: int, p: float, z: float = 5.0) -> bool:
    """``k`` successes in ``n`` trials are within ``z`` standard deviations of ``n p``."""
    return abs(k - n * p) <= z * math.sqrt(n * p * (1 - p)) + 1


# ------------------------------------------------------------------------ the pure core
def test_statistics_within_binomial_bounds() -> None:
    p = ImpairmentParams(drop_p=0.1, duplicate_p=0.05, corrupt_p=0.02, reorder_p=0.03,
                         reorder_delay_s=0.2)
    d = DirectionImpairment(p, seed="stats")
    payload = bytes(40)
    out = [d.process(i * 1e-3, payload) for i in range(N)]
    c = d.counters
    assert c.datagrams == N
    assert _binomial_ok(c.dropped, N, 0.1)
    survivors = N - c.dropped
    assert _binomial_ok(c.duplicated, survivors, 0.05)
    assert _binomial_ok(c.corrupted, survivors, 0.02)
    assert _binomial_ok(c.reordered, survivors, 0.03)
    assert sum(len(o) for o in out) == c.delivered == survivors + c.duplicated
    corrupted = sum(1 for o in out if o and o[0].data != payload)
    assert corrupted == c.corrupted  # exactly one bit each by default
    assert all(sum(bin(b).count("1") for b in o[0].data) == 1
               for o in out if o and o[0].data != payload)


def test_same_seed_same_outcome_and_directions_independent() -> None:
    p = ImpairmentParams(drop_p=0.3, jitter_s=0.01)
    a = LinkImpairment.build("offboard", 7, p, p)
    b = LinkImpairment.build("offboard", 7, p, p)
    frames = [_frame(1, i) for i in range(500)]
    ra = [a.outgoing.process(i * 0.01, f) for i, f in enumerate(frames)]
    rb = [b.outgoing.process(i * 0.01, f) for i, f in enumerate(frames)]
    assert ra == rb
    ri = [a.incoming.process(i * 0.01, f) for i, f in enumerate(frames)]
    assert [bool(x) for x in ri] != [bool(x) for x in ra]  # its own random stream
    c = LinkImpairment.build("offboard", 8, p, p)
    rc = [c.outgoing.process(i * 0.01, f) for i, f in enumerate(frames)]
    assert [bool(x) for x in rc] != [bool(x) for x in ra]


def test_delay_and_jitter_keep_order_reorder_breaks_it() -> None:
    d = DirectionImpairment(ImpairmentParams(delay_s=0.1, jitter_s=0.05), seed=3)
    times = [d.process(i * 0.01, bytes([i % 256]))[0].deliver_at_s for i in range(2000)]
    lat = [t - i * 0.01 for i, t in enumerate(times)]
    assert min(lat) >= 0.1 - 1e-12
    assert max(lat) <= 0.15 + 0.05  # never more than delay + jitter + the wait for the order
    assert all(b >= a for a, b in itertools.pairwise(times))  # FIFO
    assert 0.11 < sum(lat) / len(lat) < 0.16

    r = DirectionImpairment(ImpairmentParams(reorder_p=0.2, reorder_delay_s=0.05), seed=4)
    deliveries = [(r.process(i * 0.01, bytes([i % 256]))[0].deliver_at_s, i)
                  for i in range(1000)]
    order = [i for _, i in sorted(deliveries)]
    overtaken = sum(1 for a, b in itertools.pairwise(order) if b < a)
    assert overtaken >= 0.5 * r.counters.reordered > 0
    held = [t - i * 0.01 for t, i in deliveries if t - i * 0.01 > 1e-9]
    assert len(held) == r.counters.reordered
    assert all(math.isclose(h, 0.05) for h in held)


def test_cut_and_heartbeat_stop() -> None:
    imp = LinkImpairment.build("offboard", 1, ImpairmentParams(), ImpairmentParams(),
                               cuts_s=((1.0, 2.0),), heartbeat_stop_s=3.0)
    hb, other = _frame(0), _frame(1)
    assert msgid_of(hb) == 0 and msgid_of(other) == 2 and msgid_of(b"\xfe" * 20) is None
    for t in (0.0, 0.99, 2.0, 2.99):
        assert [x.data for x in imp.outgoing.process(t, hb)] == [hb]
        assert len(imp.incoming.process(t, other)) == 1
    for t in (1.0, 1.5, 1.999):
        assert imp.outgoing.process(t, other) == [] and imp.incoming.process(t, other) == []
    assert imp.outgoing.process(3.0, hb) == []
    assert len(imp.outgoing.process(3.0, other)) == 1
    assert len(imp.incoming.process(3.0, hb)) == 1  # the peer's heartbeats still pass
    assert imp.outgoing.counters.cut == 3 and imp.outgoing.counters.heartbeats_stopped == 1


def test_flip_bits_flips_distinct_bits() -> None:
    import random

    rng = random.Random(0)
    data = bytes(8)
    for n in (1, 3, 64, 100):
        out = flip_bits(data, n, rng)
        assert sum(bin(b).count("1") for b in out) == min(n, 64)
    assert flip_bits(b"", 3, rng) == b""


@pytest.mark.parametrize(("body", "key"), [
    ("[sim.impairment.vehicle_to_companion]\ndrop_p = 1.5",
     "sim.impairment.vehicle_to_companion.drop_p"),
    ("[sim.impairment.companion_to_vehicle]\ndelay_s = -1.0",
     "sim.impairment.companion_to_vehicle.delay_s"),
    ("[sim.impairment.companion_to_vehicle]\nloss = 0.1",
     "sim.impairment.companion_to_vehicle: unknown key"),
    ("[sim.impairment]\nlinks = [\"radio\"]", "sim.impairment.links"),
    ("[sim.impairment]\ncuts = [[2.0, 1.0]]", "sim.impairment.cuts[0]"),
])
def test_bad_impairment_config_names_the_key(tmp_path: Path, body: str, key: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(f'base = "{Path("config/paper.toml").resolve()}"\n{body}\n')
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_config(f)


def test_impairment_config_from_toml(tmp_path: Path) -> None:
    f = tmp_path / "lossy.toml"
    f.write_text(f'base = "{Path("config/paper.toml").resolve()}"\n'
                 "[sim.impairment]\nlinks = [\"offboard\", \"gcs\"]\nseed = 9\n"
                 "cuts = [[10.0, 12.5]]\nheartbeat_stop_s = 30.0\n"
                 "[sim.impairment.vehicle_to_companion]\ndrop_p = 0.1\njitter_s = 0.01\n"
                 "[sim.impairment.companion_to_vehicle]\ndelay_s = 0.02\n")
    imp = load_config(f).sim.impairment
    assert imp.links == ("offboard", "gcs") and imp.seed == 9 and imp.active
    assert imp.cuts == ((10.0, 12.5),) and imp.heartbeat_stop_s == 30.0
    assert imp.vehicle_to_companion == ImpairmentParams(drop_p=0.1, jitter_s=0.01)
    assert imp.companion_to_vehicle == ImpairmentParams(delay_s=0.02)
    assert not load_config().sim.impairment.active  # off by default


# ------------------------------------------------------------------------ over real UDP
def _impaired(**kw: object) -> ImpairmentConfig:
    to_peer = kw.pop("to_peer", ImpairmentParams())
    from_peer = kw.pop("from_peer", ImpairmentParams())
    return ImpairmentConfig(vehicle_to_companion=to_peer,  # type: ignore[arg-type]
                            companion_to_vehicle=from_peer, **kw)  # type: ignore[arg-type]


def test_drop_rate_seen_by_a_real_client(client: MavClient) -> None:
    """50 Hz ATTITUDE_QUATERNION through 30 % loss: the client counts the gaps."""
    imp = _impaired(to_peer=ImpairmentParams(drop_p=0.3), seed=5)
    with sim_with_client(client, impairment=imp) as rs:
        msgs = client.collect(2.0)
        counters = rs.call(lambda: rs.sim.links["offboard"].impairment.outgoing.counters)
    aq = [m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION"]
    sent = 2.0 * 50
    assert 0.5 * sent < len(aq) < 0.9 * sent, len(aq)
    assert counters.dropped > 0 and counters.datagrams > counters.delivered


def test_delay_seen_by_a_real_client(client: MavClient) -> None:
    """A 200 ms one-way delay: the echo of a PING takes >= 400 ms, and telemetry stamps lag."""
    imp = _impaired(to_peer=ImpairmentParams(delay_s=0.2), from_peer=ImpairmentParams(
        delay_s=0.2))
    with sim_with_client(client, impairment=imp):
        client.drain()
        t0 = time.monotonic()
        client.send(client.mav.ping_encode(123, 7, 0, 0))
        pong = client.wait_for(lambda m: m.get_type() == "PING" and m.seq == 7, 2.0)
        rtt = time.monotonic() - t0
    assert pong is not None
    assert 0.4 <= rtt < 0.9, rtt


def test_link_cut_and_heartbeat_stop_seen_by_a_real_client(client: MavClient) -> None:
    """Cut [0.6, 1.2) s: nothing sent in it arrives, and a command sent in it gets no ACK;
    from 1.8 s no more HEARTBEAT, while the other telemetry goes on. Times are the vehicle's
    send times: the stamps of the telemetry (a HEARTBEAT has none: it takes the stamp of the
    telemetry just before it)."""
    imp = _impaired(cuts=((0.6, 1.2),), heartbeat_stop_s=1.8)
    with sim_with_client(client, impairment=imp) as rs:
        client.command(511, 0, 50_000)  # HEARTBEAT at 20 Hz
        assert client.ack(511) is not None
        arrivals: list[tuple[float, str]] = []
        last_stamp_s = 0.0
        end = time.monotonic() + 2.6
        sent_in_cut = False
        while time.monotonic() < end:
            if not sent_in_cut and 0.75 < rs.call(rs.sim.now_s) < 1.0:
                client.command(400, 1)  # arm (already armed): an ACK would come back
                sent_in_cut = True
            for m in client.recv(0.02):
                if m.get_srcSystem() != 1:  # the AGV: its own node, not cut
                    continue
                if hasattr(m, "time_boot_ms"):
                    last_stamp_s = m.time_boot_ms * 1e-3
                arrivals.append((last_stamp_s, m.get_type()))
        counters = rs.call(lambda: rs.sim.links["offboard"].impairment.outgoing.counters)
    assert sent_in_cut
    stamped = [t for t, k in arrivals if k == "ATTITUDE_QUATERNION"]
    assert not [t for t in stamped if 0.6 <= t < 1.2]
    assert [t for t in stamped if t < 0.6] and [t for t in stamped if t >= 1.2]
    assert "COMMAND_ACK" not in {k for _, k in arrivals}
    assert [t for t, k in arrivals if k == "HEARTBEAT" and 1.2 <= t < 1.75]
    assert not [t for t, k in arrivals if k == "HEARTBEAT" and t >= 1.8]
    assert len([t for t in stamped if t >= 1.8]) > 20
    assert counters.cut > 0 and counters.heartbeats_stopped > 0


def test_corruption_is_rejected_by_the_receivers(client: MavClient) -> None:
    """Every datagram gets a flipped bit both ways: the client's parser (CRC) drops what
    reaches it, and the emulator counts the bad frames it receives instead of acting on them."""
    imp = _impaired(to_peer=ImpairmentParams(corrupt_p=1.0),
                    from_peer=ImpairmentParams(corrupt_p=1.0))
    with sim_with_client(client, impairment=imp) as rs:
        good = [m for m in client.collect(0.5) if m.get_srcSystem() == 1]  # not the AGV
        for _ in range(50):
            client.command(400, 1)
        time.sleep(0.3)
        c = rs.call(lambda: rs.sim.links["offboard"].counters)
    # a flipped bit in the payload or CRC fails the CRC; very few flips (e.g. in an unused
    # trailing length field) can leave a valid frame, so allow a handful
    assert len(good) <= 3
    assert c.rx_messages <= 3 and c.rx_bad + c.rx_empty + c.rx_unknown + c.rx_mavlink1 >= 47


def _lockstep_steps(client: MavClient, rs, budget_s: float) -> int:
    """Answer each camera frame with a setpoint; return how many frames were seen."""
    q = [1.0, 0.0, 0.0, 0.0]
    cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
    n = 0
    try:
        end = time.monotonic() + budget_s
        cam.settimeout(0.3)
        while rs.thread.is_alive() and time.monotonic() < end:
            try:
                hdr, _ = read_frame(cam)
            except TimeoutError:
                client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0, 0, 0.5))
                continue
            except ConnectionError:
                break
            n += 1
            client.send(client.mav.set_attitude_target_encode(
                hdr["t_us"] // 1000, 1, 1, 7, q, 0, 0, 0, 0.5))
            client.drain()
    finally:
        cam.close()
    return n


def test_lockstep_does_not_stall_when_every_setpoint_is_dropped(client: MavClient) -> None:
    """Lockstep, every setpoint lost on the way: the step is released by the client's answer
    (not by the 2 s timeout), PX4 never sees a signal."""
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=2.0,
                      impairment=_impaired(from_peer=ImpairmentParams(drop_p=1.0)))
    cfg = with_link(cfg, offboard_remote=f"127.0.0.1:{client.port}")
    t0 = time.monotonic()
    with run_sim(cfg, duration_s=2.0) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        _lockstep_steps(client, rs, 20.0)
        rs.thread.join(10.0)
    stats = rs.stop()
    assert time.monotonic() - t0 < 10.0
    assert stats.steps == 40
    assert stats.lockstep_timeouts <= 1  # step 0 may leave before the client connects
    assert stats.setpoints_received == 0


def test_lockstep_delay_counts_in_simulated_time(client: MavClient) -> None:
    """Lockstep with 120 ms delay on setpoints: the setpoint of step k reaches PX4 at
    t_k + 0.12 s simulated, so the signal age seen in ground truth is about 0.12 s at each
    frame; wall time plays no part."""
    cfg = make_config(time_mode="lockstep", lockstep_timeout_s=2.0,
                      impairment=_impaired(from_peer=ImpairmentParams(delay_s=0.12)))
    cfg = with_link(cfg, offboard_remote=f"127.0.0.1:{client.port}")
    ages: list[float] = []
    with run_sim(cfg, duration_s=1.5) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        real_pub = rs.sim.publish_frame

        async def spy(t: float) -> None:
            ages.append(rs.sim.px4.setpoint_age_s(t))
            await real_pub(t)

        rs.sim.publish_frame = spy  # type: ignore[method-assign]
        _lockstep_steps(client, rs, 20.0)
        rs.thread.join(10.0)
    stats = rs.stop()
    assert stats.steps == 30 and stats.lockstep_timeouts <= 1
    assert stats.setpoints_received >= 25
    # the step-k setpoint arrives at t_k + 0.12, between frames k+2 (t_k + 0.1) and k+3:
    # at each later frame the newest applied setpoint is 0.03 s (= 0.15 - 0.12) old
    steady = [a for a in ages[6:] if math.isfinite(a)]
    assert steady and all(math.isclose(a, 0.03, abs_tol=1e-6) for a in steady), steady


def test_shipped_lossy_variant() -> None:
    cfg = load_config(Path(__file__).resolve().parents[2] / "config" / "lossy-link.toml")
    imp = cfg.sim.impairment
    assert imp.active and imp.links == ("offboard",) and imp.cuts == ((60.0, 61.5),)
    assert imp.cuts[0][1] - imp.cuts[0][0] > cfg.sim.px4.com_of_loss_t_s  # as its header says


def test_duplicates_and_reordering_seen_by_a_real_client(client: MavClient) -> None:
    """Every datagram doubled, 30 % held back 60 ms: the client gets each ATTITUDE_QUATERNION
    twice and sees their stamps go backwards at times (the receiver's job to sort out)."""
    imp = _impaired(to_peer=ImpairmentParams(duplicate_p=1.0, reorder_p=0.3,
                                             reorder_delay_s=0.06))
    with sim_with_client(client, impairment=imp):
        msgs = client.collect(1.5)
    stamps = [m.time_boot_ms for m in msgs if m.get_type() == "ATTITUDE_QUATERNION"]
    assert len(stamps) > 40
    counts = {s: stamps.count(s) for s in set(stamps)}
    assert sum(1 for n in counts.values() if n == 2) >= 0.8 * len(counts)
    assert sum(1 for a, b in itertools.pairwise(stamps) if b < a) >= 3


def test_sim_bridge_runs_the_lossy_variant_and_logs_what_it_did() -> None:
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    p = subprocess.run(
        [sys.executable, "-m", "sim_bridge", "--config", str(root / "config" / "lossy-link.toml"),
         "--duration", "1", "--bind", "127.0.0.1", "--offboard-port", "0", "--gcs-port", "0",
         "--agv-port", "0", "--frame-port", "0", "--offboard-remote", "127.0.0.1:9",
         "--gcs-remote", "127.0.0.1:9", "--truth-remote", "127.0.0.1:9"],
        capture_output=True, text=True, timeout=60, cwd=root)
    assert p.returncode == 0, p.stderr[-2000:]
    line = next(ln for ln in p.stderr.splitlines() if "impairment offboard vehicle->peer" in ln)
    assert "'dropped': " in line and "'datagrams': 0" not in line
