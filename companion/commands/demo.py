"""``companion demo``: the emulator and the companion as two processes on loopback, in lockstep.

They meet only on sockets (docs/reference/wire.md), exactly as the companion meets a real PX4. The
demo
merges the config file and every ``--set`` override into ``DIR/config.toml`` (so an override
reaches both processes, ``sim.*`` keys the emulator and shared ``camera.*``/``target.*`` keys
both), has both programs validate it (``sim-bridge --check-config``; a key neither knows is
refused before anything flies), picks free ports, starts ``python -m sim_bridge --lockstep`` and
``python -m companion run`` on that file, waits for the flight, then scores it from the log
(ground truth recorded on ``/truth``) into ``DIR/report.json`` and the report figures.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from companion.config import DEFAULT_CONFIG, config_from_dict, read_document
from companion.config_file import merged_document
from companion.flight import fly
from companion.report.text import demo_summary

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="fly a scenario: emulator + companion in lockstep")
    p.add_argument("--scenario", default="paper",
                   help="[sim.scenarios.NAME] of the config: paper, edge, yaw-offset, ...")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds (default: sim.duration_s, one AGV period)")
    p.add_argument("--no-visibility", action="store_true",
                   help="switch the RMPC's visibility constraints off (for comparison)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for both processes, e.g. sim.agv.speed_scale=3 "
                        "(repeatable; a key neither program knows is refused)")
    p.add_argument("--inject-fault", action="append", default=[], metavar="KIND:T0:T1")
    p.add_argument("--out", type=Path, default=None, help="output dir (default out/SCENARIO)")
    p.add_argument("--no-plots", action="store_true", help="report.json only")
    p.add_argument("--live", action="store_true",
                   help="serve the flight live to Foxglove (ws://live.host:live.port)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    overrides = list(args.set)
    if args.no_visibility:
        overrides.append("rmpc.enable_visibility=false")
    out = args.out or Path("out") / (args.scenario + ("-novis" if args.no_visibility else ""))
    if args.live:
        lc = config_from_dict(merged_document(read_document(args.config), overrides)).live
        where = f"ws://{lc.host}:{lc.port}" if lc.port else f"a free port ({out}/companion.log)"
        print(f"live view: {where} (Foxglove: Open connection, Foxglove WebSocket; layout "
              "foxglove/layout.json)", flush=True)
    flight = fly(args.config, args.scenario, args.duration, out, overrides,
                 args.inject_fault, plots=not args.no_plots, live=args.live,
                 show_progress=True)
    print(f"scenario {args.scenario}:")
    for line in demo_summary(flight.report):
        print(line)
    print(f"report: {out / 'report.json'}")
    return 0
