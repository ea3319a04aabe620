"""The report headline judges each figure against its target (pure function of report.json)."""

from __future__ import annotations

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
