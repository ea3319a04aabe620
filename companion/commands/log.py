"""``companion log info LOG.mcap``: channels, counts, rates, duration (like ``mcap info``).
``companion log export --tlog OUT.tlog LOG.mcap``: the MAVLink traffic as a telemetry log.
``companion log lag LOG.mcap``: the vehicle's tilt lag (``control.lead.attitude_lag_s``)
measured from the setpoints it flew (docs/guides/tune.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from companion import CompanionError
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
    lag = lsub.add_parser(
        "lag", help="measure the vehicle's tilt lag (control.lead.attitude_lag_s) from a flight")
    lag.add_argument("log", type=Path)
    lag.add_argument("--delay", action="store_true",
                     help="also fit a pure delay before the lag (a diagnostic: the lead, "
                          "control.lead.attitude_lag_s, inverts a lag alone)")
    lag.add_argument("--max-delay", type=float, default=0.2, metavar="S",
                     help="largest pure delay searched (s, default 0.2)")
    lag.add_argument("--max-gap", type=float, default=0.5, metavar="S",
                     help="a longer pause between setpoints ends a stretch (s, default 0.5)")
    lag.add_argument("--json", action="store_true", help="print the result as JSON")
    lag.set_defaults(func=_lag)


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


def _lag(args: argparse.Namespace) -> int:
    import json

    from companion.log.lag import config_line, measure_lag

    if not (0.0 <= args.max_delay <= 2.0) or not (0.0 < args.max_gap <= 10.0):
        raise CompanionError("--max-delay must be in [0, 2] s and --max-gap in (0, 10] s")
    res = measure_lag(args.log, fit_delay=args.delay, max_delay_s=args.max_delay,
                      max_gap_s=args.max_gap)
    if args.json:
        print(json.dumps(res.to_dict(), indent=2))
        return 0
    print(f"log:       {args.log}")
    print(f"used:      {res.samples} attitude samples ({res.attitude_topic}), {res.setpoints} "
          f"setpoints, {res.stretches} stretch(es), {res.offboard_s:.1f} s in OFFBOARD")
    if res.salvage_note:
        print(f"note:      {res.salvage_note}")
    if res.dropped_nonfinite:
        print(f"dropped:   {res.dropped_nonfinite} non-finite samples")
    print(f"tau:       {res.tau_s:.3f} s  (roll {res.per_axis_tau_s[0]:.3f} s, pitch "
          f"{res.per_axis_tau_s[1]:.3f} s; squared error within 10 % of the best for "
          f"{res.tau_range_s[0]:.3f}..{res.tau_range_s[1]:.3f} s)")
    if res.fit_delay:
        print(f"delay:     {res.delay_s:.3f} s  (setpoint sent -> autopilot acting on it)")
    print(f"fit:       RMS residual {res.rms_deg:.3f} deg, variance explained "
          f"{res.variance_explained * 100:.1f} %")
    for w in res.warnings:
        print(f"warning:   {w}")
    if res.fit_delay:
        print("suggested: none from a lag fitted beside a delay; run without --delay for "
              "control.lead.attitude_lag_s")
    else:
        print(f"suggested: {config_line(res.tau_s)}")
    return 0
