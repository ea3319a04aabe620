"""Saying when the target outruns the controller (companion/control/outrun.py): the pure
check's hysteresis, the keys it names, and the report's headline row."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import load_config
from companion.control.outrun import CLEAR_S, ENTER_S, OutrunCheck, target_motion_magnitudes
from companion.control.pipeline import VelocityEstimate
from companion.report.figures import _outrun
from companion.report.headline import headline


def _run(check: OutrunCheck, speeds: list[float], dt: float = 0.05, t0: float = 0.0) -> list:
    events = []
    for i, v in enumerate(speeds):
        events += check.update(t0 + i * dt, (v, 0.0, 0.0))
    return events


def test_the_paper_bounds_cannot_follow_a_1_5_m_s_target_and_the_message_names_the_key() -> None:
    cfg = load_config("config/paper.toml")
    check = OutrunCheck.for_bounds(cfg.rmpc.eta_max, cfg.rmpc.u_max)
    assert check.bounds == (1.0, 0.3, 1.5)  # eta_max[4], u_max[3], u_max[0]
    events = _run(check, [1.5] * 40)
    assert len(events) == 1
    ev = events[0]
    assert ev.outrun and ev.quantity == "speed" and ev.t_s == pytest.approx(ENTER_S)
    msg = ev.message()
    assert "outruns the controller" in msg and "1.50 m/s exceeds the configured bound 1.00" in msg
    assert "rmpc.eta_max[4], rmpc.eta_max[5]" in msg


def test_hysteresis_no_flapping_at_the_bound() -> None:
    check = OutrunCheck((1.0, 0.3, 1.5))
    # short excursions above the bound (< ENTER_S) say nothing
    assert _run(check, [1.2] * 9 + [0.9] * 5 + [1.2] * 9) == []
    on = _run(check, [1.2] * 20, t0=10.0)
    assert [e.outrun for e in on] == [True]
    # just under the bound (above 95 % of it) keeps the verdict; well under clears it after
    # CLEAR_S
    assert _run(check, [0.97] * 60, t0=20.0) == []
    off = _run(check, [0.5] * 30, t0=30.0)
    assert [e.outrun for e in off] == [False] and off[0].t_s == pytest.approx(30.0 + CLEAR_S)


def test_turn_rate_and_acceleration_are_checked_too() -> None:
    check = OutrunCheck((3.0, 0.3, 1.5))
    ev = []
    for i in range(30):
        ev += check.update(i * 0.05, (1.5, 0.5, 0.75))  # a 1.5 m/s, 0.5 rad/s circle
    assert [(e.quantity, e.keys) for e in ev] == [("turn rate", "rmpc.u_max[3]")]
    ev = []
    for i in range(30):
        ev += check.update(i * 0.05, (1.0, None, 2.0))  # turn rate unknown this step
    assert [(e.quantity, e.keys) for e in ev] == [("acceleration", "rmpc.u_max[0], rmpc.u_max[1]")]


def test_magnitudes_from_the_pipelines_estimate() -> None:
    ft = VelocityEstimate(np.array([1.2, 0.9, 0.1]), np.array([0.3, 0.4, 0.0]), -0.5,
                          "follow_target")
    assert target_motion_magnitudes(ft) == pytest.approx((1.5, -0.5, 0.5))
    img = VelocityEstimate(np.array([0.6, 0.8, 0.0]), np.zeros(3), 0.0, "image_estimator")
    assert target_motion_magnitudes(img) == (pytest.approx(1.0), None, None)
    assert target_motion_magnitudes(None) == (None, None, None)


def test_the_report_headline_says_the_target_outran_and_which_key() -> None:
    rec = {"t_s": 3.0, "quantity": "speed", "outrun": True, "value": 1.5, "bound": 1.0,
           "unit": "m/s", "keys": "rmpc.eta_max[4], rmpc.eta_max[5]"}
    rep = {"outrun": _outrun([rec, {**rec, "t_s": 9.0, "outrun": False, "value": 0.5}])}
    row = next(r for r in headline(rep) if r.key == "outrun")
    assert row.verdict == "miss"
    assert row.figure == "no: speed 1.50 > 1.00 m/s, raise rmpc.eta_max[4], rmpc.eta_max[5]"
    ok = next(r for r in headline({"outrun": _outrun([])}) if r.key == "outrun")
    assert (ok.verdict, ok.figure) == ("pass", "yes")
    assert next(r for r in headline({}) if r.key == "outrun").verdict == "n/a"
