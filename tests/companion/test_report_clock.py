"""Report times are simulated time since the flight started, not the autopilot's boot clock
(a realistic telemetry level starts ``time_boot_ms`` at a boot offset)."""

from __future__ import annotations

from typing import Any

import pytest

from companion.report.figures import TOPIC_TRUTH, ReportSettings, compute_report

ST = ReportSettings(width_px=1000, height_px=1000, pixel_size_m=5.04e-6,
                    report_pixel_size_m=2.52e-6, visible_bound_report_px=500.0,
                    desired_depth_m=3.0)


def _truth(sim_t: float, boot_offset_s: float, with_sim_t: bool) -> dict[str, Any]:
    # the AGV starts 0.5 m ahead and is under the vehicle from t = 5 s on
    dx = 0.5 if sim_t < 5.0 else 0.0
    rec: dict[str, Any] = {
        "t_us": round((sim_t + boot_offset_s) * 1e6),
        "uav": {"pos_ned_m": [0.0, 0.0, -3.3], "q_wxyz": [1.0, 0.0, 0.0, 0.0],
                "vel_ned_m_s": [0.0, 0.0, 0.0]},
        "agv": {"pos_ned_m": [dx, 0.0, -0.3], "yaw_rad": 0.0},
    }
    if with_sim_t:
        rec["sim_t_s"] = sim_t
    return rec


@pytest.mark.parametrize(("boot_offset_s", "with_sim_t"), [(37.25, True), (0.0, False)])
def test_flight_time_and_settle_time_are_simulated_time(boot_offset_s: float,
                                                        with_sim_t: bool) -> None:
    msgs = [(TOPIC_TRUTH, 0, _truth(k * 0.05, boot_offset_s, with_sim_t)) for k in range(401)]
    rep = compute_report(msgs, ST)
    assert rep["sim_time_s"] == pytest.approx(20.0)
    assert rep["tracking"]["settle_time_s"] == pytest.approx(5.0)
