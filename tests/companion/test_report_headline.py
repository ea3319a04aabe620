"""The report headline judges each figure against its target (pure function of report.json)."""

from __future__ import annotations

import pytest

from companion.report.headline import headline


def _rep(**over: object) -> dict:
    rep = {
        "sim_time_s": 10.0,
        "visibility": {"frames": 200, "frames_outside_bound": 0, "frames_target_lost": 0,
                       "max_abs_u_px": 300.0, "max_abs_n_px": 410.4, "bound_px": 500.0},
        "tracking": {"settle_time_s": 4.0, "rms_horizontal_error_after_settle_m": 0.004,
                     "rms_height_error_after_settle_m": 0.012},
        "solver": {"solves": 200, "failures": 0, "fallbacks": 0, "recoveries": 9},
        "latency": {"frame_to_command_median_ms": 2.5, "p95_ms": 5.0},
        "safety": {"transitions": []},
    }
    rep.update(over)
    return rep


def _v(rep: dict) -> dict[str, tuple[str, str]]:
    return {r.key: (r.verdict, r.figure) for r in headline(rep)}


def test_headline_judges_each_target() -> None:
    v = _v(_rep())
    assert v["in_view"][0] == "pass" and v["worst_corner"] == ("pass", "410 px")
    assert v["settle"] == ("pass", "4.0 s")
    assert v["steady_horizontal"] == ("pass", "0.4 cm")
    assert v["steady_height"] == ("miss", "1.2 cm")  # 12 mm > 10 mm
    assert v["solver"][0] == "pass"  # 4.5 % recovery
    assert v["latency"][0] == "pass" and v["safety"] == ("pass", "none")


def test_headline_misses_and_missing_data() -> None:
    rep = _rep(visibility={"frames": 200, "frames_outside_bound": 3, "frames_target_lost": 20,
                           "max_abs_u_px": 567.0, "max_abs_n_px": 10.0, "bound_px": 500.0},
               solver={"solves": 200, "failures": 0, "fallbacks": 0, "recoveries": 11},
               tracking={"settle_time_s": None}, latency={},
               safety={"transitions": [{"to": "hover"}]})
    v = _v(rep)
    assert v["in_view"][0] == "miss" and v["worst_corner"] == ("miss", "567 px")
    assert v["time_lost"] == ("miss", "1.0 s")  # 20 frames of 50 ms
    assert v["settle"] == ("miss", "never settled")
    assert v["steady_height"][0] == "n/a" and v["latency"][0] == "n/a"
    assert v["solver"][0] == "miss"  # 5.5 % recovery
    assert v["safety"] == ("miss", "1 transitions")
    assert _v({})["in_view"][0] == "n/a"


def test_headline_judges_the_engaged_figures() -> None:
    ok = _v(_rep(engaged={"frames_outside_bound": 0, "corner_max_px": 496.4,
                          "recovery_fraction": 0.045, "fallbacks": 0}))
    assert ok["in_view_engaged"] == ("pass", "yes, worst corner 496 px")
    assert ok["recovery_engaged"] == ("pass", "4.5 %, 0 fallbacks")
    bad = _v(_rep(engaged={"frames_outside_bound": 3, "corner_max_px": 513.0,
                           "recovery_fraction": 0.07, "fallbacks": 1}))
    assert bad["in_view_engaged"] == ("miss", "no: 3 frames out, worst corner 513 px")
    assert bad["recovery_engaged"][0] == "miss"
    assert _v(_rep())["in_view_engaged"][0] == "n/a"


def test_engaged_figures_start_one_second_after_offboard() -> None:
    """compute_report: frames before OFFBOARD + 1 s (truth mode) do not count."""
    from companion.report.figures import ReportSettings, compute_report

    st = ReportSettings(1000, 1000, 5.04e-6, 2.52e-6, 500.0, 2.0)
    out, inside = [[500.0, 100.0]] * 4, [[500.0, 450.0]] * 4  # row 100: 800 px up; row 450: 98
    msgs = []
    for k in range(60):  # 3 s at 20 Hz, OFFBOARD from 0.5 s, corner out until 1.45 s
        t = k * 0.05
        msgs.append(("/truth", k, {"t_us": round(t * 1e6), "corners_px": out if t < 1.5
                                   else inside, "mode": "OFFBOARD" if t >= 0.5 else "POSCTL"}))
        msgs.append(("/control/step", k, {"t_s": t, "perception": {"status": "ok"},
                                          "rmpc": {"mode": "recovery" if t < 1.0 else "optimal",
                                                   "success": True, "solve_time_s": 1e-3,
                                                   "iterations": 3}}))
    rep = compute_report(msgs, st)
    eng = rep["engaged"]
    assert eng["t_engaged_s"] == 0.5 and eng["from_s"] == 1.5
    assert eng["frames_outside_bound"] == 0 and eng["corner_max_px"] < 500.0
    assert rep["visibility"]["frames_outside_bound"] == 30
    assert eng["recovery_fraction"] == pytest.approx(10 / 50)


def test_demo_summary_is_rounded_text_with_verdicts() -> None:
    """What ``companion demo`` prints: no Python list/dict repr, figures rounded with units,
    each headline row with its verdict, and a last line counting the misses."""
    from companion.report.text import demo_summary

    rep = _rep(tracking={"settle_time_s": 4.0, "rms_se": [0.00925537222372309, 0.0225, 0.1, 0.2],
                         "rms_horizontal_error_m": 0.10261644096588553,
                         "rms_height_error_m": 0.30182155871236904,
                         "rms_horizontal_error_after_settle_m": 0.004,
                         "rms_height_error_after_settle_m": 0.012},
               wall_time_s=54.41788417800001, real_time_factor=0.18376, controller="rmpc",
               companion_cpu_ms_per_step=13.3849, emulator_cpu_ms_per_step=7.499544,
               load_1min=5.56103515625)
    rep["solver"] = {**rep["solver"], "median_ms": 3.0245570000033695, "p95_ms": 20.68}
    text = "\n".join(demo_summary(rep))
    for raw in ("[", "{", "0.00925", "3.02455", "13.3849"):
        assert raw not in text, raw
    assert "10.0 s simulated in 54.4 s wall (0.2x real time)" in text
    assert "horizontal 10.3 cm, height 30.2 cm" in text
    assert "median 3.0 ms" in text and "companion 13.4 ms" in text
    assert "MISS  Steady height error" in text and "PASS  Settling time" in text
    assert text.splitlines()[-1].strip().startswith("1 of ")
