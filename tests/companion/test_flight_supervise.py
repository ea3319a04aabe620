"""The demo's supervision of its two processes (companion/flight.py: _supervise)."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from companion.flight import _supervise
from companion.flight_ports import FlightSockets


def test_a_failed_emulator_stops_the_companion_at_once(tmp_path: Path) -> None:
    """An emulator that exits with an error (e.g. a config it refuses) ends the flight: the
    companion is told to stop at once, and the failure is the emulator's exit code, not a
    companion that "did not exit" 30 s later."""
    comp = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    sim_cmd = [sys.executable, "-c", "import sys; sys.exit(2)"]
    with open(tmp_path / "sim.log", "wb") as out, FlightSockets() as sockets:
        ended = _supervise(sim_cmd, out, comp, {}, tmp_path, 60.0, None, lambda: None,
                           sockets)
    assert ended.sim_rc == 2
    assert ended.comp_rc == -signal.SIGTERM
    assert comp.poll() is not None
