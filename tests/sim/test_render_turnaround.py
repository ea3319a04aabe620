"""The emulator's cheaper step renders the same frames (docs/reference/emulator.md, "The step's
cost"): the rotation is scipy's to the bit, and in lockstep every frame on the socket is, pixel
for pixel, the frame of the pose its ground-truth record reports
(real sockets, real rendering)."""

from __future__ import annotations

import math
import socket
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim_bridge.app import build_camera
from sim_bridge.camera.camera import quat_to_matrix
from sim_bridge.config import with_link
from sim_bridge.physics.agv import AgvState
from tests.sim.harness import MavClient, drain_truth, make_config, read_frame, run_sim


def test_quat_to_matrix_is_scipys_bit_for_bit() -> None:
    rng = np.random.default_rng(11)
    qs = rng.normal(size=(20000, 4))
    qs[::2] /= np.linalg.norm(qs[::2], axis=1, keepdims=True)  # unit and not
    qs[1::4] *= rng.uniform(1e-3, 1e3, size=(len(qs[1::4]), 1))
    for q in qs:
        ref = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        assert np.array_equal(quat_to_matrix(q), ref), q


def _wave(t_s: float) -> list[float]:
    """A roll/pitch wave about hover (w, x, y, z): the vehicle and the view move every step."""
    roll, pitch = 0.12 * math.sin(2.0 * t_s), 0.1 * math.sin(1.5 * t_s + 1.0)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    return [cr * cp, sr * cp, cr * sp, -sr * sp]


def _fly(client: MavClient, truth: socket.socket, n_steps: int
         ) -> tuple[Any, dict[int, bytes], list[dict[str, Any]]]:
    cfg = with_link(make_config(time_mode="lockstep", lockstep_timeout_s=5.0),
                    offboard_remote=f"127.0.0.1:{client.port}",
                    truth_remote=f"127.0.0.1:{truth.getsockname()[1]}")
    frames: dict[int, bytes] = {}
    with run_sim(cfg, duration_s=n_steps * 0.05) as rs:
        client.target = ("127.0.0.1", rs.ports["offboard"])
        cam = socket.create_connection(("127.0.0.1", rs.ports["frames"]), timeout=5.0)
        cam.settimeout(0.5)
        try:
            while len(frames) < n_steps - 1:
                try:
                    hdr, payload = read_frame(cam)
                except TimeoutError:  # step 0's frame left before we connected
                    assert not frames
                    client.send(client.mav.set_attitude_target_encode(
                        0, 1, 1, 7, _wave(0.0), 0, 0, 0, 0.5))
                    cam.settimeout(5.0)
                    continue
                frames[hdr["seq"]] = payload
                if len(frames) == 2:  # OFFBOARD: the vehicle flies the wave
                    client.command(176, 1, 6)
                t_s = hdr["t_us"] * 1e-6
                client.send(client.mav.set_attitude_target_encode(
                    hdr["t_us"] // 1000, 1, 1, 7, _wave(t_s), 0, 0, 0, 0.5))
                client.drain()
        finally:
            cam.close()
        stats = rs.stop()
    assert stats is not None and stats.lockstep_timeouts == 0
    return cfg, frames, drain_truth(truth)


@pytest.mark.timeout(120)
def test_lockstep_frame_is_the_truth_pose_rendered(client: MavClient) -> None:
    """Every frame on the socket equals a fresh render of the UAV pose and the AGV of its
    ground-truth record (JSON floats round-trip exactly): frame and record describe the same
    instant (a frame of the previous step's pose would shift the ground by the vehicle's
    motion in one step: thousands of pixels)."""
    truth = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    truth.bind(("127.0.0.1", 0))
    try:
        cfg, frames, records = _fly(client, truth, n_steps=40)
    finally:
        truth.close()
    camera = build_camera(cfg)
    by_seq = {r["frame_seq"]: r for r in records}
    moved = set()
    for seq, payload in frames.items():
        r = by_seq[seq]
        a = r["agv"]
        agv = AgvState(r["sim_t_s"], a["pos_ned_m"], a["vel_ned_m_s"], a["acc_ned_m_s2"],
                       a["yaw_rad"], a["yaw_rate_rad_s"])
        frame = camera.render(np.array(r["uav"]["pos_ned_m"]), np.array(r["uav"]["q_wxyz"]),
                              agv)
        image = np.frombuffer(payload, np.uint8).reshape(frame.image.shape)
        assert np.array_equal(image, frame.image), f"frame {seq} differs from its truth pose"
        assert r["corners_px"] == frame.corners_px.tolist()
        moved.add(tuple(np.round(r["uav"]["q_wxyz"], 3)))
    assert len(frames) >= 38 and len(moved) > 10  # the view really changed along the flight
