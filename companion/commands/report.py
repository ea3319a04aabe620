"""``companion report LOG.mcap --out DIR``: figures, report.json and an HTML summary."""

from __future__ import annotations

import argparse
from pathlib import Path

from companion.config import load_config
from companion.log.reader import LogReader, NotMcapError
from companion.replay import ReplayError, replay_config
from companion.report.files import build_report
from companion.report.text import headline_lines, verdict_line


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("report", help="plots and figures of a flight log")
    p.add_argument("log", type=Path)
    p.add_argument("--out", type=Path, default=Path("out") / "report")
    p.add_argument("--config", type=Path, default=None,
                   help="camera/geometry config (default: the one recorded in the log)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    try:
        reader = LogReader(args.log, verify=False)  # only its /config is read here
    except NotMcapError as exc:
        print(f"companion: error: {exc}")
        return 2
    try:
        cfg = replay_config(reader, args.config, [])
    except ReplayError:
        cfg = load_config(None)
    finally:
        reader.close()
    args.out.mkdir(parents=True, exist_ok=True)
    from companion.progress import step_callback

    bar, cb = step_callback("report", unit="msg")
    try:
        rep = build_report(args.log, cfg, args.out, progress=cb)
    finally:
        bar.close()
    print(f"flight {args.log}:")
    for line in headline_lines(rep):
        print(line)
    print(f"  {verdict_line(rep)}")
    print(f"report: {args.out / 'report.json'}, {args.out / 'report.html'} "
          f"({len(rep.get('figures', {}))} figures)")
    return 0
