"""``companion replay LOG.mcap``: recompute a flight's commands offline and compare them.

``--from-detections`` feeds the controller the detections the flight recorded (no perception:
for tuning the controller). ``--set KEY=VALUE`` changes the config; a key given several times
is a sweep: one replay per value (every combination when several keys are swept), results side
by side in ``DIR/sweep.json`` and a table on stdout.

``--out DIR`` writes the replay's own log (``DIR/replay.mcap``: the recomputed step records and
the flight's ground truth) and the report built from it (``DIR/report.json``, plots); without
it the replay compares and prints only: writing that log cost ~0.5 ms of the replay's CPU a
step, and its report is read by nobody who did not ask for it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import time
from pathlib import Path
from typing import Any

from companion import ConfigError
from companion.config import load_config
from companion.log.reader import LogReader, NotMcapError
from companion.progress import step_callback
from companion.replay import ReplayError, replay, replay_config
from companion.replay_inputs import Perceived
from companion.report.text import replay_summary


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("replay", help="replay a log through the same perception and controller")
    p.add_argument("log", type=Path, help="MCAP log written by `companion run` / `demo`")
    p.add_argument("--config", type=Path, default=None,
                   help="config to replay with (default: the one recorded in the log)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (repeatable), e.g. --set rmpc.q_diag=[...]; "
                        "the same KEY several times sweeps its values")
    p.add_argument("--from-detections", action="store_true",
                   help="controller only: use the recorded detections instead of perception")
    p.add_argument("--in-process", action="store_true",
                   help="read the log and run perception in this process (default: a "
                        "second process, beside the controller)")
    p.add_argument("--out", type=Path, default=None,
                   help="write the replay's log (DIR/replay.mcap) and its report "
                        "(DIR/report.json) there; without it the replay compares and prints "
                        "only")
    p.add_argument("--no-plots", action="store_true")
    p.set_defaults(func=_run)


def sweep_variants(sets: list[str]) -> list[list[str]]:
    """The override lists of a sweep: a key given n times contributes n alternatives; keys
    given once apply to every variant. One variant (the list itself) without a repeated key."""
    by_key: dict[str, list[str]] = {}
    for s in sets:
        key = s.split("=", 1)[0].strip()
        if "=" not in s or not key:
            raise ConfigError(f"--set {s!r}: expected KEY=VALUE")
        by_key.setdefault(key, []).append(s)
    if all(len(v) == 1 for v in by_key.values()):
        return [list(sets)]
    return [list(combo) for combo in itertools.product(*by_key.values())]


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


def _one(args: argparse.Namespace, overrides: list[str], out: Path | None, label: str,
         perceived: list[Perceived] | None) -> dict[str, Any]:
    """One replay; with ``out``, its log and report written there."""
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.monotonic(), _cpu_s()
    bar, cb = step_callback(label)
    first: list[float] = []  # when the first step was done: the start-up's end

    def progress(done: int, total: int) -> None:
        if not first:
            first.append(time.monotonic())
        cb(done, total)

    try:
        res = replay(args.log, None if out is None else out / "replay.mcap", args.config,
                     overrides, progress=progress, from_detections=args.from_detections,
                     workers=0 if args.in_process else 1, perceived=perceived)
    finally:
        bar.close()
    wall, cpu = time.monotonic() - t0, _cpu_s() - c0
    summary = res.summary()
    summary["wall_time_s"] = wall
    # reading the config, building the controller (and the solver), the first step's inputs
    summary["startup_s"] = first[0] - t0 if first else None
    summary["cpu_time_s"] = cpu  # this process and the perception worker
    summary["cpu_ms_per_step"] = cpu * 1e3 / res.steps if res.steps else None
    summary["load_1min"] = os.getloadavg()[0]
    summary["overrides"] = overrides
    summary["log_path"] = str(args.log)
    with LogReader(args.log, verify=False) as reader:
        steps = [c for c in reader.channels if c.topic == "/control/step"]
    span = steps[0] if steps else None
    flight_s = ((span.last_log_time_ns or 0) - (span.first_log_time_ns or 0)) * 1e-9 \
        if span else 0.0
    summary["flight_time_s"] = flight_s
    summary["speed_vs_real_time"] = flight_s / wall if wall > 0 and flight_s else None
    if out is not None:
        _write_report(args, overrides, out, summary)
    return summary


def _write_report(args: argparse.Namespace, overrides: list[str], out: Path,
                  summary: dict[str, Any]) -> None:
    """``out/report.json``: the replay's summary and the report of the replay's log."""
    from companion.report.files import build_report

    if args.config:
        cfg = load_config(args.config, overrides)
    else:
        with LogReader(args.log, verify=False) as reader:  # only its /config is needed
            cfg = replay_config(reader, None, overrides)
    report: dict[str, object] = {"replay": summary}
    flight = build_report(out / "replay.mcap", cfg, out, plots=not args.no_plots)
    report.update({k: v for k, v in flight.items() if k not in ("replay",)})
    (out / "report.json").write_text(json.dumps(report, indent=2))


def _run(args: argparse.Namespace) -> int:
    out: Path | None = args.out
    try:
        variants = sweep_variants(list(args.set))
    except ConfigError as exc:
        print(f"companion: error: {exc}")
        return 2
    try:
        if len(variants) == 1:
            s = _one(args, variants[0], out, "replay", None)
            _print_single(s, out)
            return 0
        # perception is the same for every variant (run it once) unless a variant changes it
        swept = {o.split("=", 1)[0].strip() for v in variants for o in v}
        shared = not any(k.startswith(("camera.", "target.")) for k in swept)
        perceived: list[Perceived] | None = [] if shared else None
        rows = []
        for i, ov in enumerate(variants):
            label = f"variant {i + 1}/{len(variants)}"
            rows.append(_one(args, ov, None if out is None else out / f"variant-{i + 1}",
                             label, perceived))
    except (NotMcapError, ReplayError) as exc:
        print(f"companion: error: {exc}")
        return 2
    print(sweep_table(rows))
    if out is not None:
        (out / "sweep.json").write_text(json.dumps({"variants": rows}, indent=2))
        print(f"sweep: {out / 'sweep.json'}")
    return 0


def _print_single(s: dict[str, Any], out: Path | None) -> None:
    print(f"replay of {s.get('log_path', 'the log')}:")
    for line in replay_summary(s):
        print(line)
    if out is not None:
        print(f"report: {out / 'report.json'}")


def sweep_table(rows: list[dict[str, Any]]) -> str:
    """The variants side by side, one column each."""
    def f(v: Any, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    lines = [
        ("overrides", [" ".join(r["overrides"]) or "(recorded)" for r in rows]),
        ("commands changed", [f"{r['commands_changed']}/{r['commands_compared']}" for r in rows]),
        ("max |dq|", [f(r["max_quat_diff"], ".3g") for r in rows]),
        ("max |dthrust|", [f(r["max_thrust_diff"], ".3g") for r in rows]),
        ("first difference s", [f(r["first_difference_t_s"], ".2f") for r in rows]),
        ("solver modes", [" ".join(f"{k}:{v}" for k, v in sorted(r["solver_modes"].items()))
                          for r in rows]),
        ("solve ms median", [f(r["solve_ms_median"], ".2f") for r in rows]),
        ("solve ms p95", [f(r["solve_ms_p95"], ".2f") for r in rows]),
        ("mean cost", [f(r["mean_cost"], ".4g") for r in rows]),
        ("thrust min..max", [f"{f(r['thrust_min'], '.3f')}..{f(r['thrust_max'], '.3f')}"
                             for r in rows]),
        ("wall s", [f(r["wall_time_s"], ".1f") for r in rows]),
    ]
    head = ["", *[f"variant {i + 1}" for i in range(len(rows))]]
    table = [head] + [[name, *vals] for name, vals in lines]
    widths = [max(len(r[i]) for r in table) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True))
                     for r in table)
