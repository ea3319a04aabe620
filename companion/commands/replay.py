"""``companion replay LOG.mcap``: recompute a flight's commands offline and compare them."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from companion.config import load_config
from companion.log.reader import NotMcapError
from companion.replay import replay, replay_config, terminal_progress


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("replay", help="replay a log through the same perception and controller")
    p.add_argument("log", type=Path, help="MCAP log written by `companion run` / `demo`")
    p.add_argument("--config", type=Path, default=None,
                   help="config to replay with (default: the one recorded in the log)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (repeatable), e.g. --set rmpc.q_diag=[...]")
    p.add_argument("--out", type=Path, default=None, help="output dir (default out/replay)")
    p.add_argument("--no-plots", action="store_true")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    out = args.out or Path("out") / "replay"
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        res = replay(args.log, out / "replay.mcap", args.config, args.set,
                     progress=terminal_progress())
    except NotMcapError as exc:
        print(f"companion: error: {exc}")
        return 2
    wall = time.monotonic() - t0
    summary = res.summary()
    summary["wall_time_s"] = wall
    report: dict[str, object] = {"replay": summary}
    from companion.log.reader import LogReader
    from companion.report.files import build_report

    if args.config:
        cfg = load_config(args.config, args.set)
    else:
        with LogReader(args.log, verify=False) as reader:  # only its /config is needed
            cfg = replay_config(reader, None, args.set)
    flight = build_report(out / "replay.mcap", cfg, out, plots=not args.no_plots)
    report.update({k: v for k, v in flight.items() if k not in ("replay",)})
    sim_s = flight.get("sim_time_s") or 0.0
    summary["speed_vs_real_time"] = (sim_s / wall) if wall > 0 and sim_s else None
    (out / "report.json").write_text(json.dumps(report, indent=2))
    same = "identical" if summary["identical"] else "DIFFERENT"
    print(f"replayed {res.steps} steps in {wall:.1f} s: {res.commands_compared} commands "
          f"compared, {same} (max |dq| {res.max_quat_diff:.3g}, max |dthrust| "
          f"{res.max_thrust_diff:.3g}, tolerance 1e-6)")
    if res.first_difference_t_s is not None:
        print(f"first difference at t = {res.first_difference_t_s:.2f} s")
    if res.recovery.get("truncated"):
        print(f"log was cut short: {res.recovery['messages_recovered']} messages recovered")
    print(f"report: {out / 'report.json'}")
    return 0
