"""The companion's command line loads only the subcommand it runs (start-up time of a flight
and of a replay: ``certify`` alone needs scipy.optimize and the certificate)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

_PROBE = """
import sys
import companion.cli as cli
parser = cli.build_parser(cli._chosen(sys.argv[1:]))
loaded = sorted(m for m in ("companion.commands.certify", "companion.core.certificate",
                            "companion.commands.demo", "companion.commands.replay",
                            "scipy.optimize", "companion.camera", "companion.link",
                            "companion.log.writer", "tqdm", "pymavlink.dialects.v20.common")
                if m in sys.modules)
print(",".join(loaded))
"""


def _loaded(*argv: str) -> list[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True,
                         check=True, env=env, cwd=ROOT)
    return [m for m in out.stdout.strip().split(",") if m]


def test_a_replay_loads_neither_the_certificate_nor_other_subcommands() -> None:
    # nor what only a flight or a replay writing its log needs: the camera back-ends (asyncio,
    # capture), the MAVLink link and dialect, the MCAP writer, the progress bar off a terminal
    assert _loaded("-v", "replay", "flight.mcap") == ["companion.commands.replay"]


def test_no_or_an_unknown_subcommand_builds_every_subcommand() -> None:
    for argv in ((), ("--help",), ("nonsense",)):
        loaded = _loaded(*argv)
        assert "companion.commands.certify" in loaded and "companion.commands.demo" in loaded
