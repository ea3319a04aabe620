"""CPU per frame of the two frame transports (docs/reference/wire.md), each side on its own.

    python bench/frame_transport.py [--frames 400] [--transport tcp|shm] [--json]

The emulator's real ``FrameServer`` in a child process publishes 1000 x 1000 mono8 frames one
at a time, in lockstep: each waits for the client's answer (a UDP datagram), as the lockstep
emulator waits for a setpoint. The client is the companion's real ``FrameSocketSource``
(``?frames=all``, and ``&transport=shm`` for shared memory) in this process: it takes each
frame (decoded, as perception gets it) and answers. Each process's CPU time
(``getrusage``, user + system) over the frames, divided by their number, is printed: the
server's publish and send and the client's receive, copy and decode, and nothing else (no
rendering, no telemetry, no controller), so the two transports compare without a flight's
noise. Wall time per frame is printed too (it depends on the machine's load).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import resource
import socket
import sys
import time
from pathlib import Path

import numpy as np


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


async def _serve(n: int, port_file: str) -> None:
    from sim_bridge.camera.frames import FrameServer

    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.settimeout(30.0)
    images = [np.random.default_rng(i).integers(40, 150, (1000, 1000), dtype=np.uint8)
              for i in range(4)]
    async with FrameServer("127.0.0.1", 0) as srv:
        with open(port_file, "w") as f:
            f.write(f"{srv.port} {udp.getsockname()[1]}")
        while srv.n_clients < 1:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.3)  # the client's request, if any, is read
        loop = asyncio.get_running_loop()
        cpu0 = 0.0
        for seq in range(n + 10):
            if seq == 10:  # the first frames map pages and warm up
                cpu0 = _cpu_s()
            await srv.publish(seq, 50_000 * seq, images[seq % 4])
            await loop.run_in_executor(None, udp.recv, 16)  # the client's answer
        print(json.dumps({"server_cpu_ms_per_frame": (_cpu_s() - cpu0) * 1e3 / n}))


async def _client(args: argparse.Namespace, port: int, answer_port: int) -> dict[str, float]:
    from companion.camera import open_camera

    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    query = "?frames=all" + ("&transport=shm" if args.transport == "shm" else "")
    cpu0 = wall0 = 0.0
    async with open_camera(f"tcp://127.0.0.1:{port}{query}") as cam:
        for i in range(args.frames + 10):
            if i == 10:
                cpu0, wall0 = _cpu_s(), time.perf_counter()
            frame = await asyncio.wait_for(anext(cam), 30.0)
            assert frame.seq == i, (frame.seq, i)
            udp.sendto(b"x", ("127.0.0.1", answer_port))
        torn = cam.stats.torn_frames
    n = args.frames
    return {"client_cpu_ms_per_frame": (_cpu_s() - cpu0) * 1e3 / n,
            "wall_ms_per_frame": (time.perf_counter() - wall0) * 1e3 / n, "torn": torn}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--transport", choices=("tcp", "shm"), default="tcp")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--serve", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        asyncio.run(_serve(args.frames, args.serve))
        return 0
    import os
    import subprocess
    import tempfile

    port_file = os.path.join(tempfile.mkdtemp(prefix="frame-transport-"), "ports")
    srv = subprocess.Popen([sys.executable, __file__, "--frames", str(args.frames),
                            "--serve", port_file], stdout=subprocess.PIPE, text=True)
    try:
        while not os.path.exists(port_file) or not Path(port_file).read_text().strip():
            time.sleep(0.05)
        port, answer_port = map(int, Path(port_file).read_text().split())
        res = asyncio.run(_client(args, port, answer_port))
        out, _ = srv.communicate(timeout=60)
    finally:
        if srv.poll() is None:
            srv.kill()
    res.update(json.loads(out.strip().splitlines()[-1]))
    res["loadavg_1min"] = os.getloadavg()[0]
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"{args.transport}: server {res['server_cpu_ms_per_frame']:.3f} ms CPU a frame, "
              f"client {res['client_cpu_ms_per_frame']:.3f} ms CPU a frame, wall "
              f"{res['wall_ms_per_frame']:.2f} ms a frame, {res['torn']} torn, load "
              f"{res['loadavg_1min']:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
