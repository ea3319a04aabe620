"""``companion run``: the on-vehicle process."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from companion.config import load_config
from companion.control.event_loop import run_loop
from companion.control.faults import FaultWindow
from companion.control.runtime import CompanionApp
from companion.flight import positive_seconds

#: The GIL's switch interval of the control process (Python's default 5 ms). The control loop
#: shares the GIL with the log writer thread: a frame that arrives while the writer encodes waits
#: until the writer is asked to let go, up to a whole interval. Four back-to-back pairs of 60 s
#: `bench/latency.py` runs on a quiet machine, 5 ms against 0.5 ms: frame -> command median
#: 2.92, 3.18, 3.09, 3.15 against 2.72, 2.77, 3.39, 2.91 ms, p95 5.43, 7.93, 6.09, 5.94 against
#: 4.47, 5.18, 8.04, 5.01 ms, companion CPU no higher (docs/reference/logging.md): a small gain
#: inside the machine's run-to-run spread, at no cost.
GIL_SWITCH_INTERVAL_S = 0.0005


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("run", help="run the companion against an autopilot and a camera")
    p.add_argument("--config", type=Path, default=None, help="config file (default: paper)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set rmpc.eps=0.11 (repeatable)")
    p.add_argument("--mavlink", default=None,
                   help="MAVLink connection: udpin:0.0.0.0:14540, udpout:HOST:PORT, "
                        "tcp:HOST:PORT, /dev/ttyACM0,921600 (default: mavlink.url)")
    p.add_argument("--camera", default="tcp://127.0.0.1:5700",
                   help="camera: tcp://HOST:PORT (frame socket; ?transport=shm: its frames "
                        "through shared memory, same host), device index, file, rtsp://")
    p.add_argument("--log", type=Path, default=None,
                   help="MCAP log file (default: logging.dir/flight-<time>.mcap)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    p.add_argument("--camera-timeout", type=positive_seconds, default=5.0, metavar="S",
                   help="stop when no camera frame arrives for S seconds once frames have "
                        "flowed (default 5; a lockstep flight sets it above the emulator's "
                        "sim.lockstep_timeout_s, so the emulator's timeout acts first)")
    p.add_argument("--truth-port", type=int, default=None,
                   help="record the emulator's ground truth from this UDP port (scoring only)")
    p.add_argument("--inject-fault", action="append", default=[], metavar="KIND:T0:T1",
                   help="failure injection for tests: solver:T0:T1 or solver-hang:T0:T1 (seconds "
                        "after first frame)")
    p.add_argument("--live", action="store_true",
                   help="serve the log's channels live over the Foxglove WebSocket protocol "
                        "(live.host:live.port, default 127.0.0.1:8765; see [live] config)")
    p.add_argument("--ready-file", type=Path, default=None,
                   help="write this file once every socket is open (for orchestration)")
    p.add_argument("--progress-file", type=Path, default=None,
                   help="keep 'ELAPSED_S STEPS' in this file (for orchestration)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config, args.set)
    if args.live:
        cfg = dataclasses.replace(cfg, live=dataclasses.replace(cfg.live, enabled=True))
    text = Path(cfg.source).read_text() if cfg.source else ""
    log_path = args.log or Path(cfg.logging.dir) / time.strftime("flight-%Y%m%d-%H%M%S.mcap")
    app = CompanionApp(
        cfg, mavlink_url=args.mavlink, camera_url=args.camera, log_path=log_path,
        truth_port=args.truth_port, duration_s=args.duration,
        idle_timeout_s=args.camera_timeout,
        faults=tuple(FaultWindow.parse(f) for f in args.inject_fault), config_text=text,
        ready_file=args.ready_file, progress_file=args.progress_file,
    )
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    rc = run_loop(app.run())
    if app.cpu_ms_per_step is not None:
        print(f"companion: {app.steps} steps, CPU {app.cpu_ms_per_step:.2f} ms per step "
              "(getrusage, all threads and the solver process)")
    return rc
