"""``sim-bridge`` / ``python -m sim_bridge``: run the emulator.

With no arguments: realtime, the ``paper`` scenario of ``config/paper.toml``, PX4 SITL default
ports (it logs which). Exits 0 at the end of ``--duration`` or on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import socket
import sys
from typing import TYPE_CHECKING

from sim_bridge import SimBridgeError
from sim_bridge.config import EmulatorConfig, load_config, with_link, with_sim

if TYPE_CHECKING:
    from sim_bridge.app import SimBridge

log = logging.getLogger("sim_bridge")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sim-bridge", description=__doc__.splitlines()[0])
    p.add_argument("--config", help="scenario TOML (default: config/paper.toml)")
    p.add_argument("--scenario", help="name in [sim.scenarios.*] (default: sim.scenario)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true",
                      help="simulated time (docs/reference/wire.md)")
    mode.add_argument("--realtime", action="store_true", help="wall-clock time")
    p.add_argument("--duration", type=float, help="seconds of boot time to run "
                   "(default: sim.duration_s)")
    p.add_argument("--start", choices=("airborne", "ground"), help="override sim.start")
    p.add_argument("--bind", default="0.0.0.0", help="listen address (default 0.0.0.0)")
    p.add_argument("--offboard-port", type=int, help="local UDP port of the offboard link")
    p.add_argument("--offboard-remote", help="HOST:PORT the offboard link sends to")
    p.add_argument("--gcs-port", type=int, help="local UDP port of the GCS link")
    p.add_argument("--gcs-remote", help="HOST:PORT the GCS link sends to")
    p.add_argument("--agv-port", type=int, help="local UDP port of the AGV node")
    frames = p.add_mutually_exclusive_group()
    frames.add_argument("--frame-port", type=int, help="TCP port of the camera frame server")
    frames.add_argument("--frame-fd", type=int,
                        help="an inherited listening TCP socket (its file descriptor) to serve "
                             "the camera frames on: the port is chosen and held by the process "
                             "that starts the emulator (``companion demo``), so no other "
                             "process can take it in between")
    p.add_argument("--truth-remote", help="HOST:PORT for ground-truth JSON")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--cv-threads", type=int, default=1,
                   help="OpenCV threads for the render (default 1; 0: OpenCV's own pool). "
                        "The frames are the same either way (docs/reference/emulator.md)")
    p.add_argument("--check-config", action="store_true",
                   help="validate the config (and --scenario) the way a run would, print a "
                        "summary and exit: 0 if valid, 2 with the offending key if not")
    return p


def check_config(cfg: EmulatorConfig) -> str:
    """What a run would refuse beyond the file's own validation (the signing key file), and
    a one-line summary of the emulator's view of the config."""
    if cfg.sim.signing.enabled:
        cfg.sim.signing.key()
    s = cfg.sim
    return (f"sim-bridge: config OK ({cfg.source or 'default'}): scenario {cfg.scenario.name} "
            f"uav_pose {list(cfg.scenario.uav_pose)}, agv {s.agv.trajectory} x{s.agv.speed_scale:g}"
            f", target {cfg.target.pattern}, attitude_tau {s.vehicle.attitude_tau_s:g} s, "
            f"gust {s.disturbance.gust_amplitude_m_s2:g} m/s^2, random "
            f"{s.disturbance.random_bound_m_s2:g} m/s^2, seed {s.seed}")


async def _run(sim: SimBridge, duration: float | None) -> None:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, task.cancel)
    try:
        async with sim:
            stats = await sim.run(duration)
            log.info("done: t=%.2f s, %d steps, %d lockstep timeouts, %d setpoints, "
                     "%d commands, %d frames", stats.t_s, stats.steps, stats.lockstep_timeouts,
                     stats.setpoints_received, stats.commands, stats.frames)
    except asyncio.CancelledError:
        log.info("stopped by signal")


def _render_threads(n: int) -> None:
    """OpenCV's threads (``cv2.setNumThreads``; 1 by default: its pool splits each warp and
    resize of a 1000 x 1000 frame across threads that spin between the calls, 3.9 against 2.8
    ms of CPU per render, load 6; docs/reference/emulator.md, "The step's cost"). OpenCV
    splits by rows and computes every pixel the same either way."""
    import cv2

    if n < 0:
        raise SimBridgeError(f"--cv-threads: must be >= 0, got {n}")
    cv2.setNumThreads(n if n > 0 else -1)


def inherited_listener(fd: int) -> socket.socket:
    """The listening TCP socket of file descriptor ``fd`` (``--frame-fd``), or a clear error."""
    try:
        sock = socket.socket(fileno=fd)
    except OSError as e:
        raise SimBridgeError(f"--frame-fd {fd}: not an open socket ({e.strerror})") from e
    if (sock.type != socket.SOCK_STREAM
            or not sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN)):
        sock.detach()  # not ours to close
        raise SimBridgeError(f"--frame-fd {fd}: not a listening TCP socket")
    return sock


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        cfg = load_config(args.config, scenario=args.scenario)
        # the clock and the start first: --check-config judges the run they ask for (e.g. a
        # camera rate that lockstep would ignore)
        if args.lockstep:
            cfg = with_sim(cfg, time_mode="lockstep")
        elif args.realtime:
            cfg = with_sim(cfg, time_mode="realtime")
        if args.start:
            cfg = with_sim(cfg, start=args.start)
        if args.check_config:
            print(check_config(cfg))
            return 0
        from sim_bridge.app import SimBridge  # not needed (nor its imports) to check a config

        _render_threads(args.cv_threads)

        changes = {k: v for k, v in {
            "offboard_local_port": args.offboard_port, "offboard_remote": args.offboard_remote,
            "gcs_local_port": args.gcs_port, "gcs_remote": args.gcs_remote,
            "agv_local_port": args.agv_port, "frame_port": args.frame_port,
            "truth_remote": args.truth_remote}.items() if v is not None}
        cfg = with_link(cfg, **changes)
        if args.duration is not None and not args.duration > 0:
            raise SimBridgeError("--duration: must be > 0")
        frame_sock = None if args.frame_fd is None else inherited_listener(args.frame_fd)
        asyncio.run(_run(SimBridge(cfg, bind_host=args.bind, frame_sock=frame_sock),
                         args.duration))
    except SimBridgeError as e:
        log.error("%s", e)
        return 2
    except KeyboardInterrupt:
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
