"""The emulator in lockstep with a trivial hover controller, as the issue states the target.

    python bench/lockstep.py [--duration 30] [--json] [--config config/realistic.toml]
                             [--thrust 0.5]

Starts ``python -m sim_bridge --lockstep`` (the real process: physics, PX4 state machine,
telemetry streams, AGV, 1000 x 1000 frames over TCP) and a minimal client in this process that
reads each frame and answers with a level hover SET_ATTITUDE_TARGET over UDP. Reports wall time
per simulated step (median from the frame arrival times), frames/s and the ratio to real time.
Target: <= 2 ms median per step. The client's own work (reading a 1 MB frame, sending one
datagram) is inside the figure, so it is an upper bound on the emulator's share. The emulator
process's own CPU time (``getrusage(RUSAGE_CHILDREN)``) per simulated step is printed too: it
does not depend on the machine's load the way wall time does. ``--thrust``: the client's
collective thrust (the vehicle's true hover thrust keeps it in the air, e.g. 0.573 with
``config/realistic.toml``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import struct
import subprocess
import sys
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

HEADER = struct.Struct("<4sBBHIQHHII")


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def read_exact(sock: socket.socket, view: memoryview, n: int) -> memoryview:
    """Fill ``view[:n]`` from the socket (no per-chunk allocation)."""
    got = 0
    while got < n:
        k = sock.recv_into(view[got:n])
        if k == 0:
            raise EOFError
        got += k
    return view[:n]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--profile", default=None, help="write the emulator's cProfile here")
    ap.add_argument("--config", default=None, help="scenario TOML for the emulator")
    ap.add_argument("--thrust", type=float, default=0.5, help="the client's hover thrust")
    args = ap.parse_args()
    p_comp, p_sim = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    p_frame = free_port(socket.SOCK_STREAM)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", p_comp))
    prof = ["-m", "cProfile", "-o", args.profile] if args.profile else []
    conf = ["--config", args.config] if args.config else []
    cmd = [sys.executable, *prof, "-m", "sim_bridge", *conf, "--lockstep",
           "--duration", str(args.duration), "--bind", "127.0.0.1", "--offboard-port", str(p_sim),
           "--offboard-remote", f"127.0.0.1:{p_comp}",
           "--gcs-port", str(free_port(socket.SOCK_DGRAM)),
           "--gcs-remote", f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
           "--agv-port", str(free_port(socket.SOCK_DGRAM)), "--frame-port", str(p_frame),
           "--truth-remote", f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}", "--log-level", "WARNING"]
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    sim = subprocess.Popen(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    q = [1.0, 0.0, 0.0, 0.0]
    hover = mav.set_attitude_target_encode(0, 1, 1, 7, q, 0.0, 0.0, 0.0, args.thrust).pack(mav)
    try:
        deadline = time.monotonic() + 30.0
        while True:
            try:
                tcp = socket.create_connection(("127.0.0.1", p_frame), timeout=1.0)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        tcp.settimeout(5.0)
        arrivals: list[float] = []
        stamps_us: list[int] = []
        buf = memoryview(bytearray(64 << 20))
        while True:
            try:
                head = HEADER.unpack(read_exact(tcp, buf, HEADER.size))
                read_exact(tcp, buf, head[8])
            except (EOFError, TimeoutError, OSError):
                break
            arrivals.append(time.perf_counter())
            stamps_us.append(head[5])
            udp.sendto(hover, ("127.0.0.1", p_sim))
        sim.wait(timeout=30.0)
    finally:
        if sim.poll() is None:
            sim.kill()
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    emu_cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    gaps = np.diff(np.array(arrivals[5:])) * 1e3
    step_s = 0.05
    # with camera latency/drops a frame does not arrive every step: wall time per simulated step
    sim_steps = (stamps_us[-1] - stamps_us[5]) / (step_s * 1e6)
    per_step_ms = (arrivals[-1] - arrivals[5]) * 1e3 / sim_steps
    res = {
        "steps": len(arrivals),
        "wall_per_sim_step_ms": float(per_step_ms),
        "loadavg_1min": round(os.getloadavg()[0], 2),
        "median_ms": float(np.median(gaps)),
        "p95_ms": float(np.percentile(gaps, 95)),
        "frames_per_s": float(1e3 / np.median(gaps)),
        "real_time_ratio": float(step_s * 1e3 / np.median(gaps)),
        "target_ms": 2.0,
        # whole process (start-up included) over every simulated step
        "emulator_cpu_ms_per_sim_step": float(emu_cpu_s * 1e3 / (args.duration / step_s)),
    }
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"lockstep emulator + trivial hover client, {res['steps']} steps: median "
              f"{res['median_ms']:.2f} ms/step (target 2), p95 {res['p95_ms']:.2f} ms, "
              f"{res['frames_per_s']:.0f} frames/s, {res['real_time_ratio']:.1f}x real time; "
              f"{res['wall_per_sim_step_ms']:.2f} ms wall per simulated step, emulator CPU "
              f"{res['emulator_cpu_ms_per_sim_step']:.2f} ms per simulated step, "
              f"load {res['loadavg_1min']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
