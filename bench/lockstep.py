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

``--lockstep-timeout S``: the emulator's ``sim.lockstep_timeout_s`` (10 s by default with
``--digest``). ``--cv-threads N``: the emulator's OpenCV threads (``sim-bridge --cv-threads``;
1 by default, 0 = OpenCV's own pool; the frames are the same either way).

``--wrap CMD``: the emulator runs under ``CMD`` (e.g. ``"valgrind --tool=callgrind
--callgrind-out-file=cg.out"``; the client then waits minutes, not seconds, for its frames):
instruction counts of the real process, which the machine's load does not change; two
durations' difference is the cost of the steps between them (docs/reference/emulator.md).

``--transport shm``: the client asks for the frames through the emulator's shared memory
(docs/reference/wire.md) and copies each out of its slot; the digest hashes the same header
(with the payload's CRC-32) and pixels, so both transports give the same digest.

``--digest``: an identity check of the emulator's output. The client switches the vehicle to
OFFBOARD and flies a slow attitude wave (so the vehicle and the view move), and prints one
SHA-256 over every frame (header and pixels) and every MAVLink datagram of the offboard link
from frame sequence number 20 on (after the start-up, which depends on when the client
connects; the wave and the OFFBOARD request follow the frames' sequence numbers too).
Lockstep makes it deterministic when every step delivers its frame (an ideal camera's timing:
no latency, no drops; a step that delivers none does not wait for the client) and no step
times out (give ``sim.lockstep_timeout_s`` room on a loaded machine): the same code and config
then give the same digest; a change meant to keep the emulator's behaviour must keep it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import mmap
import os
import resource
import shlex
import socket
import struct
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np
from fastcrc.crc32 import iso_hdlc as crc32
from pymavlink.dialects.v20 import common as mavlink2

HEADER = struct.Struct("<4sBBHIQHHII")
ANNOUNCE = struct.Struct("<4sBBHIIIQI")  # the shared-memory segment (docs/reference/wire.md)
SHM_REQUEST = struct.pack("<4sBBH", b"IBVQ", 1, 1, 0)
# ``python -c _PROFILED OUT ARGS...``: the emulator under cProfile timed by the process's CPU
# clock (a wall-clock profile on a loaded machine charges other processes' time to whatever
# line was running when the scheduler took the core away).
_PROFILED = """import cProfile, runpy, sys, time
out = sys.argv[1]
sys.argv = ["sim_bridge", *sys.argv[2:]]
p = cProfile.Profile(time.process_time)
try:
    p.runcall(runpy.run_module, "sim_bridge", run_name="__main__", alter_sys=True)
except SystemExit:
    pass
finally:
    p.dump_stats(out)
"""


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


def _digest_step(digest: Any, udp: socket.socket, head: tuple[int, ...], buf: memoryview,
                 mav: mavlink2.MAVLink, p_sim: int, index: int) -> None:
    """Hash the frame just read and the datagrams that came before it (from frame ``index`` =
    its sequence number 20 on), then answer it: OFFBOARD requested at frame 10, a slow
    roll/pitch wave about hover. Counted by the emulator's frame sequence number, not by
    arrival: whether the client connected before step 0's frame left does not shift it."""
    grams = []
    while True:
        try:
            grams.append(udp.recv(65536))
        except BlockingIOError:
            break
    if index >= 20:
        digest.update(repr(head).encode())
        digest.update(bytes(buf[:head[8]]))
        for g in grams:
            if not (g[:1] == b"\xfd" and int.from_bytes(g[7:10], "little") == 2):
                digest.update(g)  # SYSTEM_TIME carries the wall clock's Unix time: left out
    t_s = 0.05 * index
    roll, pitch = 0.08 * math.sin(0.7 * t_s), 0.06 * math.sin(0.5 * t_s + 1.0)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    q = [cr * cp, sr * cp, cr * sp, -sr * sp]
    to = ("127.0.0.1", p_sim)
    if index == 10:  # before the setpoint, which releases the step: handled within the step
        udp.sendto(mav.command_long_encode(1, 1, 176, 0, 1, 6, 0, 0, 0, 0, 0).pack(mav), to)
    udp.sendto(mav.set_attitude_target_encode(head[5] // 1000, 1, 1, 7, q, 0.0, 0.0, 0.0,
                                              0.5).pack(mav), to)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--profile", default=None,
                    help="write the emulator's cProfile here (CPU time: load-independent)")
    ap.add_argument("--config", default=None, help="scenario TOML for the emulator")
    ap.add_argument("--thrust", type=float, default=0.5, help="the client's hover thrust")
    ap.add_argument("--cv-threads", type=int, default=1,
                    help="the emulator's OpenCV threads (sim-bridge --cv-threads; 0: its pool)")
    ap.add_argument("--transport", choices=("tcp", "shm"), default="tcp",
                    help="the frames over TCP or through the emulator's shared memory")
    ap.add_argument("--wrap", default=None,
                    help="a command the emulator runs under, e.g. \"valgrind --tool=callgrind "
                         "--callgrind-out-file=cg.out\" (instruction counts: load-independent)")
    ap.add_argument("--digest", action="store_true",
                    help="fly an attitude wave in OFFBOARD and print the output's SHA-256")
    ap.add_argument("--lockstep-timeout", type=float, default=None,
                    help="the emulator's sim.lockstep_timeout_s (default: the config's; 10 s "
                         "with --digest, so that a loaded machine cannot time a step out)")
    return ap.parse_args(argv)


def _timeout_config(args: argparse.Namespace) -> str | None:
    """The config the emulator reads: with a lockstep timeout to set, a variant of the
    config that sets only the timeout."""
    timeout_s = args.lockstep_timeout if args.lockstep_timeout is not None else (
        10.0 if args.digest else None)
    config: str | None = args.config
    if timeout_s is None:
        return config
    base = os.path.abspath(config or os.path.join(os.path.dirname(__file__), "..",
                                                  "config", "paper.toml"))
    variant = os.path.join(tempfile.mkdtemp(prefix="lockstep-"), "config.toml")
    with open(variant, "w", encoding="utf-8") as f:
        f.write(f"base = {json.dumps(base)}\n[sim]\nlockstep_timeout_s = {timeout_s}\n")
    return variant


def _emulator_cmd(args: argparse.Namespace, p_sim: int, p_comp: int, p_frame: int) -> list[str]:
    """The emulator's command line: lockstep, every link on loopback (unused ones on free
    ports), optionally under cProfile."""
    conf = ["--config", args.config] if args.config else []
    entry = ["-c", _PROFILED, args.profile] if args.profile else ["-m", "sim_bridge"]
    return [*shlex.split(args.wrap or ""), sys.executable, *entry, *conf, "--lockstep",
            "--duration", str(args.duration), "--bind", "127.0.0.1", "--offboard-port", str(p_sim),
            "--offboard-remote", f"127.0.0.1:{p_comp}",
            "--gcs-port", str(free_port(socket.SOCK_DGRAM)),
            "--gcs-remote", f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
            "--agv-port", str(free_port(socket.SOCK_DGRAM)), "--frame-port", str(p_frame),
            "--truth-remote", f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
            "--log-level", "WARNING", "--cv-threads", str(args.cv_threads)]


def _connect_frames(p_frame: int, wait_s: float = 30.0) -> socket.socket:
    """The frame socket, retried while the emulator starts (``wait_s``)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return socket.create_connection(("127.0.0.1", p_frame), timeout=1.0)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class _Ring:
    """The emulator's shared-memory frame ring, read as docs/reference/wire.md says."""

    def __init__(self, tcp: socket.socket, head: bytes) -> None:
        _, _, self.flags, _, self.n, self.stride, self.off, size, name_len = ANNOUNCE.unpack(head)
        name = bytearray(name_len)
        read_exact(tcp, memoryview(name), name_len)
        with open(name.decode(), "rb") as f:
            self.mm = mmap.mmap(f.fileno(), size, prot=mmap.PROT_READ)
        self.gens = [np.frombuffer(self.mm, np.uint64, 1, 4096 + i * self.stride)
                     for i in range(self.n)]

    def read(self, head: tuple[Any, ...], buf: memoryview) -> bool:
        """Copy the notice's frame into ``buf``; False if its slot was torn or lapped."""
        slot, n = head[3], head[8]
        base = 4096 + slot * self.stride
        g1 = int(self.gens[slot][0])
        if g1 & 1 or HEADER.unpack_from(self.mm, base + 16)[4] != head[4]:
            return False
        buf[:n] = self.mm[base + self.off:base + self.off + n]
        return int(self.gens[slot][0]) == g1


def _read_record(tcp: socket.socket, buf: memoryview, ring: list[_Ring],
                 digest: bool) -> tuple[Any, ...]:
    """The next frame's header, its payload in ``buf`` (over TCP or out of the ring);
    a shared-memory frame's header as the TCP record's (the CRC computed for the digest)."""
    while True:
        raw = bytes(read_exact(tcp, buf, HEADER.size))
        if raw[:4] == b"IBVA":
            ring[:] = [_Ring(tcp, raw)]
            continue
        head = HEADER.unpack(raw)
        if raw[:4] == b"IBVF":
            read_exact(tcp, buf, head[8])
            return head
        if not ring[0].read(head, buf):
            raise RuntimeError(f"frame {head[4]}: shared-memory slot torn or lapped")
        crc = crc32(buf[:head[8]]) if digest else head[9]
        return (b"IBVF", head[1], head[2], 0, *head[4:9], crc)


def _client_loop(args: argparse.Namespace, tcp: socket.socket, udp: socket.socket,
                 mav: mavlink2.MAVLink, hover: bytes, p_sim: int,
                 digest: Any) -> tuple[list[float], list[int]]:
    """Read every frame until the emulator ends and answer it (hover, or the digest's wave):
    the frames' arrival times (perf_counter) and sim stamps (us)."""
    tcp.settimeout(300.0 if args.wrap else 5.0)
    arrivals: list[float] = []
    stamps_us: list[int] = []
    buf = memoryview(bytearray(64 << 20))
    udp.setblocking(False)
    # a long lockstep timeout (--digest sets 10 s) may hold step 0 for us: release it
    release = args.digest or args.lockstep_timeout is not None
    if release:
        tcp.settimeout(1.0)
    ring: list[_Ring] = []
    if args.transport == "shm":
        tcp.sendall(SHM_REQUEST)
    while True:
        try:
            head = _read_record(tcp, buf, ring, args.digest)
        except TimeoutError:
            if release and not arrivals:  # step 0's frame left before we connected
                udp.sendto(hover, ("127.0.0.1", p_sim))
                tcp.settimeout(60.0)
                continue
            break
        except (EOFError, OSError):
            break
        arrivals.append(time.perf_counter())
        stamps_us.append(head[5])
        if len(arrivals) == 1:  # from now on only the emulator's end (EOF) ends the run
            tcp.settimeout(60.0)
        if args.digest:
            _digest_step(digest, udp, head, buf, mav, p_sim, head[4])
        else:
            udp.sendto(hover, ("127.0.0.1", p_sim))
    return arrivals, stamps_us


def _fly(args: argparse.Namespace, digest: Any) -> tuple[list[float], list[int], float]:
    """Start the emulator and fly the client against it: arrival times, sim stamps and the
    emulator's CPU seconds (getrusage of the children)."""
    p_comp, p_sim = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    p_frame = free_port(socket.SOCK_STREAM)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", p_comp))
    cmd = _emulator_cmd(args, p_sim, p_comp, p_frame)
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    sim = subprocess.Popen(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    q = [1.0, 0.0, 0.0, 0.0]
    hover = mav.set_attitude_target_encode(0, 1, 1, 7, q, 0.0, 0.0, 0.0, args.thrust).pack(mav)
    try:
        tcp = _connect_frames(p_frame, 900.0 if args.wrap else 30.0)
        arrivals, stamps_us = _client_loop(args, tcp, udp, mav, hover, p_sim, digest)
        sim.wait(timeout=300.0 if args.wrap else 30.0)
    finally:
        if sim.poll() is None:
            sim.kill()
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    emu_cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return arrivals, stamps_us, emu_cpu_s


def _result(arrivals: list[float], stamps_us: list[int], emu_cpu_s: float,
            duration_s: float) -> dict[str, Any]:
    gaps = np.diff(np.array(arrivals[5:])) * 1e3
    step_s = 0.05
    # with camera latency/drops a frame does not arrive every step: wall time per simulated step
    sim_steps = (stamps_us[-1] - stamps_us[5]) / (step_s * 1e6)
    per_step_ms = (arrivals[-1] - arrivals[5]) * 1e3 / sim_steps
    return {
        "steps": len(arrivals),
        "wall_per_sim_step_ms": float(per_step_ms),
        "loadavg_1min": round(os.getloadavg()[0], 2),
        "median_ms": float(np.median(gaps)),
        "p95_ms": float(np.percentile(gaps, 95)),
        "frames_per_s": float(1e3 / np.median(gaps)),
        "real_time_ratio": float(step_s * 1e3 / np.median(gaps)),
        "target_ms": 2.0,
        # whole process (start-up included) over every simulated step
        "emulator_cpu_ms_per_sim_step": float(emu_cpu_s * 1e3 / (duration_s / step_s)),
    }


def _print(res: dict[str, Any], as_json: bool) -> None:
    if as_json:
        print(json.dumps(res, indent=2))
    else:
        print(f"lockstep emulator + trivial hover client, {res['steps']} steps: median "
              f"{res['median_ms']:.2f} ms/step (target 2), p95 {res['p95_ms']:.2f} ms, "
              f"{res['frames_per_s']:.0f} frames/s, {res['real_time_ratio']:.1f}x real time; "
              f"{res['wall_per_sim_step_ms']:.2f} ms wall per simulated step, emulator CPU "
              f"{res['emulator_cpu_ms_per_sim_step']:.2f} ms per simulated step, "
              f"load {res['loadavg_1min']}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.config = _timeout_config(args)
    digest = hashlib.sha256()
    arrivals, stamps_us, emu_cpu_s = _fly(args, digest)
    res = _result(arrivals, stamps_us, emu_cpu_s, args.duration)
    if args.digest:
        res["digest_sha256"] = digest.hexdigest()
        print(f"emulator output digest (frames 20.., {len(stamps_us)} frames): "
              f"{res['digest_sha256']}")
    _print(res, args.json)
    return 0

if __name__ == "__main__":
    sys.exit(main())
