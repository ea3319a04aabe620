"""``companion log info LOG.mcap``: channels, counts, rates, duration (like ``mcap info``).
``companion log export --tlog OUT.tlog LOG.mcap``: the MAVLink traffic as a telemetry log."""

from __future__ import annotations

import argparse
from pathlib import Path

from companion.log.reader import LogReader, NotMcapError


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("log", help="inspect a flight log")
    lsub = p.add_subparsers(dest="log_command", required=True)
    info = lsub.add_parser("info", help="channels, counts, rates, time range")
    info.add_argument("log", type=Path)
    info.set_defaults(func=_info)
    exp = lsub.add_parser("export", help="export the MAVLink traffic as a telemetry log (.tlog)")
    exp.add_argument("--tlog", type=Path, required=True, metavar="OUT.tlog",
                     help="tlog to write (MAVProxy / QGroundControl / MAVExplorer format)")
    exp.add_argument("--time", choices=("auto", "log"), default="auto",
                     help="auto: Unix time from the autopilot's SYSTEM_TIME when logged; "
                          "log: the log's own clock")
    exp.add_argument("log", type=Path)
    exp.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    from companion.log.tlog import export_tlog

    res = export_tlog(args.log, args.tlog, time_base=args.time)
    span = (res.last_us - res.first_us) * 1e-6
    print(f"wrote {res.frames} MAVLink frames ({len(res.types)} types, {span:.1f} s) to "
          f"{res.path}; time base: {res.time_base}")
    if res.skipped:
        print(f"skipped {res.skipped} frames that did not decode")
    for name, n in res.types.items():
        print(f"  {name:<28} {n:>7}")
    return 0


def _info(args: argparse.Namespace) -> int:
    try:
        reader = LogReader(args.log)
    except NotMcapError as exc:
        print(f"companion: error: {exc}")
        return 2
    with reader:
        rec = reader.recovery
        chans = sorted(reader.channels, key=lambda c: c.topic)
    t0 = rec.first_log_time_ns or 0
    t1 = rec.last_log_time_ns or 0
    print(f"file:      {args.log} ({rec.bytes_total} bytes)")
    state = "cut short, salvaged" if rec.truncated else "complete"
    damaged = f", {rec.corrupt_chunks} damaged chunk(s) skipped" if rec.corrupt_chunks else ""
    print(f"state:     {state}: {rec.messages} messages{damaged}")
    if rec.truncated and rec.stop_reason:
        print(f"           read {rec.bytes_used} of {rec.bytes_total} bytes: {rec.stop_reason}")
    print(f"duration:  {(t1 - t0) * 1e-9:.3f} s  [{t0} .. {t1}] ns")
    print(f"channels:  {len(chans)}")
    w = max((len(c.topic) for c in chans), default=10)
    print(f"  {'topic':<{w}}  {'count':>7}  {'rate Hz':>8}  schema [encoding]")
    for c in chans:
        print(f"  {c.topic:<{w}}  {c.count:>7}  {c.rate_hz:>8.2f}  {c.schema_name} "
              f"[{c.message_encoding}]")
    return 0
