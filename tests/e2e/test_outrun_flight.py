"""A target faster than the configured bounds is said to outrun the controller, in the safety
log and in the report's headline (docs/guides/vehicle-limits.md): the paper's config (1 m/s
velocity bound) behind an AGV on a straight line at 1.5 m/s, one lockstep flight. The same
flight logs the vehicle's limits the companion read from the emulator (PARAM_VALUE on the
MAVLink topics like every message, and /control/vehicle_limits)."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import DEFAULT_CONFIG
from companion.flight import run_demo
from companion.log.reader import LogReader
from companion.report.headline import headline

pytestmark = pytest.mark.slow


def test_paper_config_behind_a_1_5_m_s_line_says_the_target_outran_it(tmp_path: Path) -> None:
    rep = run_demo(DEFAULT_CONFIG, "paper", 4.0, tmp_path,
                   ['sim.agv.trajectory="line"', "sim.agv.speed_scale=5"], [], plots=False)
    with LogReader(tmp_path / "flight.mcap") as r:
        safety = [m.data for m in r.messages(topics=["/control/safety"])]
        params = [m.data["fields"] for m in r.messages(topics=["/mavlink/in/PARAM_VALUE"])]
        limits = [m.data for m in r.messages(topics=["/control/vehicle_limits"])]
    outrun = [s["message"] for s in safety if s.get("name") == "outrun"]
    assert outrun, [s["message"] for s in safety]
    assert "speed 1.50 m/s exceeds the configured bound 1.00 m/s" in outrun[0]
    assert "raise rmpc.eta_max[4], rmpc.eta_max[5]" in outrun[0]
    row = next(v for v in headline(rep) if v.key == "outrun")
    assert row.verdict == "miss" and "rmpc.eta_max[4]" in row.figure
    # the vehicle's limits were read (paper.toml: read, not used for the bounds)
    assert {p["param_id"] for p in params} >= {"MPC_XY_VEL_MAX", "MPC_ACC_HOR", "MPC_THR_HOVER"}
    assert len(limits) == 1 and limits[0]["params"]["MPC_XY_VEL_MAX"] == 12.0
    assert not limits[0]["from_autopilot"] and limits[0]["u_max"] == [1.5, 1.5, 1.5, 0.3]
