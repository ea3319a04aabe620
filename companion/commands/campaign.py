"""``companion campaign``: controllers x scenarios x seeds of lockstep flights, on Dask.

Each run is a ``companion demo`` flight in ``OUT/runs/RUN_ID`` (own ports, own folder);
finished runs are skipped, so the same command resumes a campaign. Writes ``OUT/results.csv``,
``OUT/summary.md`` and ``OUT/plots/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from companion.campaign.scenarios import (
    DEFAULT_CAMPAIGN,
    REPO_ROOT,
    Controller,
    load_campaign,
)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("campaign", help="fly controllers x scenarios x seeds on Dask")
    p.add_argument("--campaign", type=Path, default=DEFAULT_CAMPAIGN,
                   help="campaign file (default: config/campaigns/default.toml)")
    p.add_argument("--out", type=Path, default=Path("out/campaign"), help="output folder")
    p.add_argument("--seeds", type=int, default=None, help="seeds 0..N-1 (default: the file's)")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds per flight (default: the file's duration_s)")
    p.add_argument("--controllers", default=None, help="comma-separated subset")
    p.add_argument("--controller", action="append", default=[], metavar="NAME[:KEY=VALUE;...]",
                   help="fly these controllers instead of the file's (repeatable), e.g. "
                        "--controller paper --controller 'novis:rmpc.enable_visibility=false'")
    p.add_argument("--scenarios", default=None, help="comma-separated subset")
    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes (default: every core)")
    p.add_argument("--address", default=None,
                   help="Dask scheduler of an existing cluster, e.g. tcp://10.0.0.5:8786")
    p.add_argument("--keep-logs", action="store_true", help="keep each run's flight.mcap")
    p.add_argument("--retry-errors", action="store_true", help="fly failed runs again")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--summary-only", action="store_true",
                   help="rebuild table, summary and plots from the finished runs (metrics "
                        "recomputed from each run's report.json); fly nothing")
    p.set_defaults(func=_run)


def parse_controller(text: str) -> Controller:
    """``NAME[:KEY=VALUE;KEY=VALUE...]`` -> a controller (named override list)."""
    from companion import CompanionError

    name, _, rest = text.partition(":")
    name = name.strip()
    if not name or not all(c.isalnum() or c in "-_." for c in name):
        raise CompanionError(f"--controller {text!r}: NAME[:KEY=VALUE;...], the name of "
                             "letters, digits, - _ .")
    sets = tuple(x.strip() for x in rest.split(";") if x.strip())
    if any("=" not in x for x in sets):
        raise CompanionError(f"--controller {text!r}: overrides are KEY=VALUE")
    return Controller(name, sets)


def _csv(v: str | None) -> list[str] | None:
    return None if v is None else [x.strip() for x in v.split(",") if x.strip()]


def _run(args: argparse.Namespace) -> int:
    from companion import CompanionError
    from companion.campaign.runner import finished_result, rescore
    from companion.campaign.summary import write_plots, write_summary, write_table

    if args.seeds is not None and args.seeds < 1:
        raise CompanionError("--seeds: must be >= 1")
    if args.workers is not None and args.workers < 1:
        raise CompanionError("--workers: must be >= 1")
    if args.duration is not None and not args.duration > 0:
        raise CompanionError("--duration: must be > 0")
    camp = load_campaign(args.campaign)
    if args.controller:
        camp = dataclasses.replace(camp, controllers=tuple(
            parse_controller(c) for c in args.controller))
    out: Path = args.out
    specs = camp.runs(out.resolve(), seeds=None if args.seeds is None else range(args.seeds),
                      controllers=_csv(args.controllers), scenarios=_csv(args.scenarios),
                      duration_s=args.duration, keep_logs=args.keep_logs)
    out.mkdir(parents=True, exist_ok=True)
    # the command that flies this matrix (a summary-only rebuild shows the flying command)
    argv = [a for a in sys.argv[1:] if a not in ("--summary-only", "--retry-errors")]
    command = "companion " + " ".join(shlex.quote(a) for a in argv) \
        if Path(sys.argv[0]).name in ("companion", "__main__.py") else ""
    load0 = os.getloadavg()
    if args.summary_only:
        rows = [rescore(r, s.out_dir) for s in specs
                if (r := finished_result(s)) is not None]
        stats = None
    else:
        from companion.campaign.engine import run_campaign

        rows, stats = run_campaign(specs, workers=args.workers, address=args.address,
                                   progress=not args.no_progress,
                                   retry_errors=args.retry_errors)
    try:
        shown = Path(args.campaign).resolve().relative_to(REPO_ROOT)
    except ValueError:
        shown = Path(args.campaign)
    notes = [f"Campaign file `{shown}`, {len(specs)} runs in the matrix, "
             f"{len(rows)} finished."]
    notes += _engine_notes(out, specs, rows, stats, load0)
    write_table(rows, out / "results.csv")
    write_plots(rows, out / "plots")
    write_summary(rows, out / "summary.md", title=f"Campaign: {out.name}", command=command,
                  notes=notes)
    ok = sum(1 for r in rows if r.get("status") == "ok")
    print(f"campaign: {len(rows)} runs ({ok} ok, {len(rows) - ok} errors); "
          f"{out / 'results.csv'}, {out / 'summary.md'}, {out / 'plots'}")
    if stats is not None and stats.flown:
        print(f"campaign: {stats.flown} flights in {stats.wall_s:.0f} s on {stats.workers} "
              f"worker(s): {stats.flights_per_minute:.2f} flights/min")
    return 0


def _engine_notes(out: Path, specs: Sequence[Any], rows: list[dict[str, Any]], stats: Any,
                  load0: tuple[float, float, float]) -> list[str]:
    """The summary's note on the engine: this invocation's flights (also kept in
    ``engine.json``), or the last flying invocation's when this one flew nothing."""
    notes: list[str] = []
    if stats is not None and stats.flown:
        fpm = stats.flights_per_minute
        load1 = os.getloadavg()
        flown_ids = {s.run_id for s in specs}
        cpu = sum(float(r.get("cpu_s") or 0.0) for r in rows if r.get("run_id") in flown_ids)
        notes.append(f"Last invocation: {stats.flown} flights in {stats.wall_s:.0f} s wall on "
                     f"{stats.workers} worker(s): {fpm:.2f} flights/min ({stats.skipped} "
                     f"skipped as finished); CPU of the runs' processes {cpu:.0f} s in all "
                     f"(matrix); machine load average (1, 5, 15 min) "
                     f"{', '.join(f'{x:.1f}' for x in load0)} at the start, "
                     f"{', '.join(f'{x:.1f}' for x in load1)} at the end "
                     f"({os.cpu_count()} cores).")
        meta = {"flown": stats.flown, "skipped": stats.skipped, "workers": stats.workers,
                "wall_s": stats.wall_s, "flights_per_minute": fpm, "cpu_s_runs": cpu,
                "load_start": load0, "load_end": load1, "cores": os.cpu_count(),
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        (out / "engine.json").write_text(json.dumps(meta, indent=2))
    elif (out / "engine.json").is_file():  # the last flying invocation's figures
        try:
            meta = json.loads((out / "engine.json").read_text())
            notes.append(f"Last flying invocation: {meta['flown']} flights in "
                         f"{meta['wall_s']:.0f} s wall on {meta['workers']} worker(s): "
                         f"{meta['flights_per_minute']:.2f} flights/min"
                         + (f"; machine load average (1, 5, 15 min) "
                            f"{', '.join(f'{x:.1f}' for x in meta['load_start'])} at the start, "
                            f"{', '.join(f'{x:.1f}' for x in meta['load_end'])} at the end"
                            if "load_start" in meta else "")
                         + ".")
        except (ValueError, KeyError, TypeError):
            pass
    return notes
