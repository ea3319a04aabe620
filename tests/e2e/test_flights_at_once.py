"""Two lockstep flights started at the same moment both fly (campaign workers do this).

With probed ports (bind to 0, close, hand the number to a child) two workers could be handed the
same port and one emulator could not bind it; now every port is chosen by the process that binds
it or held by the orchestrator until the emulator serves it (companion/flight_ports.py).
"""

from __future__ import annotations

import re
import threading
from pathlib import Path

import pytest

from companion.config import DEFAULT_CONFIG
from companion.flight import READY_FILE, Flight, fly
from companion.flight_ports import read_ready

pytestmark = pytest.mark.slow


def test_two_flights_started_at_once_both_fly_on_their_own_ports(tmp_path: Path) -> None:
    results: dict[int, Flight | BaseException] = {}
    start = threading.Barrier(2)

    def one(i: int) -> None:
        start.wait()
        try:
            results[i] = fly(DEFAULT_CONFIG, "paper", 2.0, tmp_path / f"f{i}", [], [],
                             plots=False)
        except BaseException as exc:  # reported below with the flight's number
            results[i] = exc

    threads = [threading.Thread(target=one, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=900.0)
    wiring = []
    for i in range(2):
        flight = results[i]
        assert isinstance(flight, Flight), f"flight {i}: {flight!r}"
        assert flight.report["sim_time_s"] > 1.5
        sim_log = (flight.folder / "sim.log").read_text()
        m = re.search(r"-> 127\.0\.0\.1:(\d+), GCS .* frames tcp :(\d+), truth udp -> "
                      r"127\.0\.0\.1:(\d+)", sim_log)
        assert m is not None, sim_log[:2000]
        ready = read_ready(flight.folder / READY_FILE)
        assert ready is not None
        # the emulator sent to the ports the companion bound and reported
        assert (int(m.group(1)), int(m.group(3))) == (ready.mavlink_port, ready.truth_port)
        wiring.append((int(m.group(1)), int(m.group(2)), int(m.group(3))))
    assert len({p for w in wiring for p in w}) == 6
