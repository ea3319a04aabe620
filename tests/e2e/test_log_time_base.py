"""A lockstep log on a PX4-like telemetry link keeps one time base (issue 14, item 3).

With ``[sim.telemetry] level = "realistic"`` the autopilot's clock started 37.25 s before the
flight, PX4's stream rates apply and SYSTEM_TIME arrives at 1 Hz. Every record of the log must
lie on the autopilot's clock inside the flight: none at 0 (written before the first stamp),
none on the companion's monotonic clock (the rejected-frame channel was, hours away), so
Foxglove and ``companion log info`` show the flight's real length. SYSTEM_TIME is logged (not
rejected) and anchors the tlog export to Unix time.
"""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.tlog import export_tlog

pytestmark = pytest.mark.slow

DURATION_S = 3.0


def test_every_record_is_on_the_autopilots_clock(tmp_path: Path) -> None:
    sim = tmp_path / "sim.toml"
    sim.write_text(f'base = "{DEFAULT_CONFIG}"\n[sim]\nlockstep_timeout_s = 10.0\n'
                   '[sim.telemetry]\nlevel = "realistic"\n')
    rep = run_demo(DEFAULT_CONFIG, "paper", DURATION_S, tmp_path, [], [], plots=False,
                   sim_config=sim)
    assert rep["steps"] > 0.9 * DURATION_S * 20
    times: dict[str, list[int]] = {}
    rejected: Counter[str] = Counter()
    with open(tmp_path / "flight.mcap", "rb") as f:
        for _, ch, m in make_reader(f).iter_messages(log_time_order=False):
            times.setdefault(ch.topic, []).append(m.log_time)
            if ch.topic == "/mavlink/rejected":
                rejected[m.data.decode()[:60]] += 1
    frames = times["/perception/input"]
    t0, t1 = min(frames), max(frames)
    assert t0 > 30e9, "the autopilot's clock (boot offset 37.25 s) stamps the frames"
    for topic, ts in times.items():
        # nothing before the flight's first frame by more than the pre-frame traffic, nothing
        # after its end by more than the shutdown
        assert min(ts) >= t0 - 2e9 and max(ts) <= t1 + 2e9, (topic, min(ts), max(ts), t0, t1)
    assert len(times.get("/mavlink/in/SYSTEM_TIME", [])) >= 2
    assert not rejected, rejected
    res = export_tlog(tmp_path / "flight.mcap", tmp_path / "flight.tlog")
    assert res.time_base == "SYSTEM_TIME"
    assert abs(res.first_us * 1e-6 - time.time()) < 3600, "tlog dated by the autopilot's clock"
