"""The whole emulator in lockstep, read from the wire as docs/reference/wire.md describes it: camera
frames (TCP), ground truth (UDP JSON), FOLLOW_TARGET from the AGV's own sysid, telemetry."""

from __future__ import annotations

import itertools
import math
import socket
from typing import Any

import numpy as np

from sim_bridge.config import with_link
from tests.sim.harness import MavClient, drain_truth, make_config, read_frame, run_sim


def test_lockstep_world_on_the_wire(client: MavClient) -> None:
    truth = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    truth.bind(("127.0.0.1", 0))
    truth.settimeout(2.0)
    cfg = with_link(make_config(time_mode="lockstep", lockstep_timeout_s=2.0),
                    offboard_remote=f"127.0.0.1:{client.port}",
                    truth_remote=f"127.0.0.1:{truth.getsockname()[1]}")
    n_steps = 30
    frames: list[dict[str, Any]] = []
    records: list[dict[str, Any]] = []
    follow: list[Any] = []
    local_pos: dict[int, Any] = {}
    try:
        with run_sim(cfg, duration_s=n_steps * 0.05) as rs:
            client.target = ("127.0.0.1", rs.ports["offboard"])
            cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
            q = [0.98078528, 0.0, 0.0, 0.19509032]
            cam.settimeout(0.5)
            try:
                while len(frames) < n_steps - 1:
                    try:
                        hdr, payload = read_frame(cam)
                    except TimeoutError:
                        # step 0's frame left before we connected: release that step
                        assert not frames
                        client.send(client.mav.set_attitude_target_encode(0, 1, 1, 7, q, 0, 0,
                                                                          0, 0.5))
                        cam.settimeout(5.0)
                        continue
                    frames.append(hdr)
                    assert len(payload) == hdr["w"] * hdr["h"] * (3 if hdr["enc"] == 1 else 1)
                    # answer the frame: the emulator steps
                    client.send(client.mav.set_attitude_target_encode(
                        hdr["t_us"] // 1000, 1, 1, 7, q, 0, 0, 0, 0.5))
                    for m in client.collect(0.005):
                        if m.get_type() == "FOLLOW_TARGET":
                            follow.append(m)
                        elif m.get_type() == "LOCAL_POSITION_NED":
                            local_pos[m.time_boot_ms] = m
            finally:
                cam.close()
            records += drain_truth(truth)
    finally:
        truth.close()
    # frames: one per step, stamped with simulated time, +1 sequence
    skipped = frames[0]["seq"]
    assert [f["t_us"] for f in frames] == [50_000 * (k + skipped) for k in range(len(frames))]
    assert [f["seq"] for f in frames] == list(range(skipped, skipped + len(frames)))
    assert frames[0]["w"] == 1000 and frames[0]["h"] == 1000
    # ground truth: one record per frame, same stamp and sequence
    by_seq = {r["frame_seq"]: r for r in records}
    for f in frames:
        r = by_seq[f["seq"]]
        assert r["t_us"] == f["t_us"]
        assert r["mode"] == "POSCTL" and r["armed"] is True
        assert len(r["corners_px"]) == 4 and isinstance(r["target_in_image"], bool)
        assert len(r["uav"]["q_wxyz"]) == 4 and len(r["agv"]["pos_ned_m"]) == 3
        lp = local_pos.get(f["t_us"] // 1000)
        if lp is not None:  # telemetry and truth describe the same simulated instant
            np.testing.assert_allclose([lp.x, lp.y, lp.z], r["uav"]["pos_ned_m"], atol=1e-5)
    r0 = by_seq[frames[0]["seq"]]
    assert r0["target_in_image"] is True  # the paper's start sees the AGV
    # the AGV: its own sysid, 10 Hz of simulated time
    assert follow, "no FOLLOW_TARGET received"
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in follow} == {(42, 1)}
    stamps = sorted({m.timestamp for m in follow})
    assert all(math.isclose(b - a, 100, abs_tol=1) for a, b in itertools.pairwise(stamps))
