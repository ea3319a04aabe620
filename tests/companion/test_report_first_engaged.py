"""The first problem in OFFBOARD (the first applied solve) is reported beside the first problem
of the flight (solved during the pre-flight stream, never applied)."""

from __future__ import annotations

from typing import Any

from companion.campaign.runner import metrics_row
from companion.report.figures import ReportSettings, compute_report

ST = ReportSettings(width_px=1000, height_px=1000, pixel_size_m=1e-5, report_pixel_size_m=1e-5,
                    visible_bound_report_px=250.0, desired_depth_m=2.0)


def _flight(modes: list[str], engaged_from: int) -> list[tuple[str, int, dict[str, Any]]]:
    """One truth record and one control step per 50 ms; OFFBOARD from step ``engaged_from``."""
    msgs: list[tuple[str, int, dict[str, Any]]] = []
    for k, mode in enumerate(modes):
        t = 0.05 * k
        msgs.append(("/truth", int(t * 1e9), {
            "t_us": int(t * 1e6), "sim_t_s": t, "frame_seq": k,
            "mode": "OFFBOARD" if k >= engaged_from else "POSCTL",
            "corners_px": [[490.0, 490.0], [510.0, 490.0], [510.0, 510.0], [490.0, 510.0]]}))
        msgs.append(("/control/step", int(t * 1e9), {
            "t_s": t, "frame_seq": k, "perception": {"status": "ok"},
            "offboard": "active" if k >= engaged_from else "preflight",
            "rmpc": {"mode": mode, "success": mode != "fallback", "solve_time_s": 0.002,
                     "iterations": 5}}))
    return msgs


def test_first_problem_in_offboard_is_reported_beside_the_first_of_the_flight() -> None:
    # infeasible during the pre-flight stream, feasible from the switch on
    rep = compute_report(_flight(["recovery"] * 20 + ["optimal"] * 40, engaged_from=20), ST)
    assert rep["engagement"]["first_solve_mode"] == "recovery"
    assert rep["engaged"]["first_solve_mode"] == "optimal"
    row = metrics_row(rep)
    assert row["first_feasible"] is False
    assert row["first_feasible_engaged"] is True
    assert row["first_solve_mode_engaged"] == "optimal"
    assert row["recovery_fraction_engaged"] == 0.0

    # still infeasible at the switch: both say so
    rep = compute_report(_flight(["recovery"] * 25 + ["optimal"] * 35, engaged_from=20), ST)
    row = metrics_row(rep)
    assert row["first_feasible"] is False and row["first_feasible_engaged"] is False
    assert row["recovery_fraction_engaged"] == 5 / 40


def test_a_flight_never_in_offboard_has_no_first_engaged_problem() -> None:
    rep = compute_report(_flight(["optimal"] * 10, engaged_from=99), ST)
    row = metrics_row(rep)
    assert row["first_feasible"] is True
    assert row["first_feasible_engaged"] is None


def test_a_frame_exactly_one_second_after_offboard_counts_in_both_sections() -> None:
    """The engagement section (autopilot clock ``t_us``) and the engaged section (``sim_t_s``)
    judge the same frames: a corner out exactly at OFFBOARD + 1 s is counted by both, whatever
    way the float sums round (a campaign run had 1 frame out in one and 0 in the other)."""
    msgs = _flight(["optimal"] * 60, engaged_from=23)  # OFFBOARD at 1.15 s: 1.15 + 1.0 > 2.15
    k = 43  # the frame at 2.15 s
    for topic, _, rec in msgs:
        if topic == "/truth" and rec["frame_seq"] == k:
            rec["t_us"] = 2_150_000
            rec["sim_t_s"] = 2.15
            rec["corners_px"] = [[490.0, 490.0], [510.0, 490.0], [510.0, 800.0], [490.0, 510.0]]
    rep = compute_report(msgs, ST)
    assert rep["engagement"]["frames_corner_outside_after_grace"] == 1
    assert rep["engaged"]["frames_outside_bound"] == 1
    assert rep["engaged"]["corner_max_px"] > ST.visible_bound_report_px
