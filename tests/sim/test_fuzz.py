"""10^4 random, truncated and bit-flipped datagrams: the emulator keeps running, counts them
right, and still answers afterwards."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from tests.sim.harness import MavClient, RunningSim, sim_with_client

N_FUZZ = 10_000
BATCH = 50  # below what the default socket receive buffer holds


def _oracle_valid(data: bytes) -> int:
    """Messages an independent fresh robust parser accepts as real MAVLink 2 ones."""
    p = mavlink2.MAVLink(None)
    p.robust_parsing = True
    n = 0
    for m in p.parse_buffer(data) or []:
        t = m.get_type()
        if t == "BAD_DATA" or t.startswith("UNKNOWN"):
            continue
        if m.get_msgbuf()[0] == 0xFD:
            n += 1
    return n


def _wait_received(rs: RunningSim, n: int, timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if rs.call(lambda: rs.sim.links["offboard"].counters.rx_datagrams) >= n:
            return
        time.sleep(0.01)
    c = rs.call(lambda: rs.sim.links["offboard"].counters)
    raise AssertionError(f"emulator did not receive every datagram: {n} sent, {c}")


@pytest.mark.slow
def test_ten_thousand_bad_packets(client: MavClient) -> None:
    rng = np.random.default_rng(2024)
    gcs = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    good_cmd = gcs.command_long_encode(1, 1, 31999, 0, 1, 2, 3, 4, 5, 6, 7).pack(gcs)
    good_sp = gcs.set_attitude_target_encode(0, 1, 1, 7, [1, 0, 0, 0], 0, 0, 0, 0.5).pack(gcs)
    datagrams: list[bytes] = []
    for i in range(N_FUZZ):
        kind = i % 3
        base = good_cmd if i % 2 else good_sp
        if kind == 0:  # random bytes, sometimes starting with a MAVLink magic byte
            d = bytearray(rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8))
            if rng.random() < 0.5:
                d[0] = 0xFD if rng.random() < 0.5 else 0xFE
        elif kind == 1:  # truncated good frame
            d = bytearray(base[: int(rng.integers(1, len(base)))])
        else:  # 1-3 flipped bits
            d = bytearray(base)
            for _ in range(int(rng.integers(1, 4))):
                bit = int(rng.integers(0, 8 * len(d)))
                d[bit // 8] ^= 1 << (bit % 8)
        datagrams.append(bytes(d))
    oracle = sum(_oracle_valid(d) for d in datagrams)
    assert oracle <= 5  # CRC-16 + crc_extra: mutated frames essentially never pass

    valid_every = 20  # interleave real heartbeats from a GCS
    hb = gcs.heartbeat_encode(6, 8, 0, 0, 0, 3)
    with sim_with_client(client) as rs:
        sent = 0
        valid = 0
        for start in range(0, N_FUZZ, BATCH):
            for j, d in enumerate(datagrams[start:start + BATCH]):
                client.send_raw(d)
                sent += 1
                if (start + j) % valid_every == 0:
                    client.send_raw(hb.pack(gcs))
                    sent += 1
                    valid += 1
            _wait_received(rs, sent)
            client.drain()
        c = rs.call(lambda: rs.sim.links["offboard"].counters)
        assert c.rx_datagrams == sent
        assert c.rx_messages == valid + oracle
        rejected = c.rx_bad + c.rx_unknown + c.rx_mavlink1 + c.rx_empty + c.rx_foreign
        assert rejected >= N_FUZZ - oracle
        assert rs.thread.is_alive()
        # still alive and answering: one ACK for a good command, telemetry flowing
        client.drain()
        client.command(31999)
        ack = client.ack(31999, 1.0)
        assert ack is not None and ack.result == 3
        assert client.wait_for(lambda m: m.get_type() == "HEARTBEAT", 2.0) is not None
