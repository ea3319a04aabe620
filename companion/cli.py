"""``companion`` command line: thin dispatch to one module per subcommand.

Each subcommand lives in ``companion/commands/<name>.py`` and exposes
``add_parser(subparsers)`` (registers its arguments and sets ``func``), where ``func(args)``
returns the process exit status.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from companion import CompanionError
from companion.core.errors import CoreError

SUBCOMMANDS = ("certify", "run", "demo", "replay", "report", "log", "campaign")


def build_parser(names: Sequence[str] = SUBCOMMANDS) -> argparse.ArgumentParser:
    """The parser with the subcommands ``names`` (default: all)."""
    parser = argparse.ArgumentParser(
        prog="companion", description="RMPC visual-servoing companion for PX4 (Yang & Li 2024)."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in names:
        try:
            mod = importlib.import_module(f"companion.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"companion.commands.{name}":
                raise
            continue
        mod.add_parser(sub)
    return parser


def _chosen(argv: Sequence[str]) -> Sequence[str]:
    """Only the named subcommand's module when the command line names one: each imports what
    its work needs (``certify`` scipy.optimize and the certificate, ``report`` matplotlib...),
    and a flight's or a replay's process need not load the others' (start-up time)."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return (first,) if first in SUBCOMMANDS else SUBCOMMANDS


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(_chosen(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except (CompanionError, CoreError) as exc:
        print(f"companion: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
