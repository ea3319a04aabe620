"""Figures of a flight (``report.json``), computed from its log.

Input: the decoded messages of a flight log, ``(topic, log_time_ns, payload dict)``, in any
order. Visibility and tracking figures come from the emulator's ground truth (``/truth``), never
from what the companion believed; solver, latency and link figures come from the companion's own
records (``/control/step``, ``/mavlink/out/SET_ATTITUDE_TARGET``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

TOPIC_TRUTH = "/truth"
TOPIC_STEP = "/control/step"
TOPIC_SAT_OUT = "/mavlink/out/SET_ATTITUDE_TARGET"
TOPIC_OUTRUN = "/control/outrun"  # companion/control/outrun.py


@dataclass(frozen=True)
class ReportSettings:
    """Camera geometry needed to express true corner pixels in the paper's pixels."""

    width_px: int
    height_px: int
    pixel_size_m: float
    report_pixel_size_m: float
    visible_bound_report_px: float
    desired_depth_m: float
    settle_window_s: float = 10.0
    #: the companion's configured hover thrust: commanded thrust / hover = commanded g's
    hover_thrust: float = 0.5
    g_m_s2: float = 9.81


def compute_report(messages: Iterable[tuple[str, int, Mapping[str, Any]]],
                   st: ReportSettings) -> dict[str, Any]:
    truth: list[Mapping[str, Any]] = []
    steps: list[Mapping[str, Any]] = []
    sat_times: list[int] = []
    outrun: list[Mapping[str, Any]] = []
    for topic, t_ns, payload in messages:
        if topic == TOPIC_TRUTH:
            truth.append(payload)
        elif topic == TOPIC_STEP:
            steps.append(payload)
        elif topic == TOPIC_SAT_OUT:
            sat_times.append(t_ns)
        elif topic == TOPIC_OUTRUN:
            outrun.append(payload)
    truth.sort(key=lambda r: r["t_us"])
    steps.sort(key=lambda r: r["t_s"])
    out: dict[str, Any] = {
        # simulated time flown: the emulator's clock starts at 0 with the flight ("t_us" is the
        # autopilot's boot clock, which a realistic telemetry level starts at a boot offset)
        "sim_time_s": _sim_t(truth[-1]) if truth else 0.0,
        "truth_records": len(truth),
        "steps": len(steps),
    }
    out["visibility"] = _visibility(truth, steps, st)
    out["tracking"] = _tracking(truth, st)
    out["solver"] = _solver(steps)
    out["latency"] = _latency(steps)
    span_s = out["sim_time_s"] or math.nan
    out["mavlink"] = {
        "set_attitude_target_sent": len(sat_times),
        "rate_hz": len(sat_times) / span_s if span_s and math.isfinite(span_s) else 0.0,
    }
    out["safety"] = _safety(steps)
    out["engaged"] = _engaged(truth, steps, st)
    out["engagement"] = _engagement(truth, steps, st)
    out["agv"] = _agv(truth)
    out["outrun"] = _outrun(outrun)
    return out


def _outrun(events: list[Mapping[str, Any]]) -> dict[str, Any]:
    """What ``/control/outrun`` said: every quantity the target outran the configured bounds
    in (its largest value, the bound, the keys to change), from the companion's own records."""
    by: dict[str, dict[str, Any]] = {}
    for e in sorted(events, key=lambda e: float(e.get("t_s", 0.0))):
        if not e.get("outrun"):
            continue
        q = str(e.get("quantity"))
        d = by.setdefault(q, {"quantity": q, "first_t_s": e.get("t_s"), "value": 0.0,
                              "bound": e.get("bound"), "unit": e.get("unit"),
                              "keys": e.get("keys")})
        d["value"] = max(float(d["value"]), float(e.get("value") or 0.0))
    return {"events": len(events), "outrun": list(by.values())}


def _sim_t(rec: Mapping[str, Any]) -> float:
    """Simulated time (s since the flight started) of a truth record. Records from emulators
    that predate ``sim_t_s`` carry only ``t_us``, which was simulated time then."""
    t = rec.get("sim_t_s")
    return float(t) if t is not None else float(rec["t_us"]) * 1e-6


ENGAGE_GRACE_S = 1.0
"""Figures after engagement start this long after the first step in OFFBOARD (issue 11's
acceptance: every corner inside "after the first second of offboard")."""


_T_TOL_S = 1e-6
"""Time comparisons at the engagement boundaries allow one microsecond (the records' clock):
a frame exactly at OFFBOARD + grace counts as after it in every section, whichever of the
float sums ``t_eng + grace``, ``t_us * 1e-6`` and ``sim_t_s`` rounds up."""


def _engaged(truth: list[Mapping[str, Any]], steps: list[Mapping[str, Any]],
             st: ReportSettings) -> dict[str, Any]:
    """Figures over the part of the flight the controller flew: from the first frame in
    OFFBOARD (+ :data:`ENGAGE_GRACE_S` for the visibility figures).

    ``corner_max_px``: the largest ``|u_px|, |n_px|`` of any true corner (paper pixels);
    ``frames_outside_bound``: frames with a corner outside the visible area;
    ``recovery_fraction``: recovery solves / solves over the active steps; ``fallbacks``;
    ``first_solve_mode``: the mode of the first solve in OFFBOARD, the first one whose input
    is applied (``optimal`` = its hard problem was feasible: where the certificate's recursive
    feasibility starts; the solves of the pre-flight stream before it are never applied)."""
    # the autopilot's own mode (ground truth) when recorded; else the companion's view, which
    # lags by up to a HEARTBEAT period
    # Truth records are in simulated time, steps in the companion's (autopilot) time: the
    # steps are matched to the truth through the frame they were computed from when both
    # carry ``frame_seq``, else by time.
    eng = next((r for r in truth if r.get("mode") == "OFFBOARD"), None)
    t_eng: float | None
    if eng is not None:
        t_eng = _sim_t(eng)
    else:
        t_eng = next((float(s["t_s"]) for s in steps if s.get("offboard") == "active"), None)
    if t_eng is None:
        return {"t_engaged_s": None}
    t0 = t_eng + ENGAGE_GRACE_S
    late = [r for r in truth if _sim_t(r) >= t0 - _T_TOL_S]
    vis = _visibility(late, [], st)
    seq_t = {r["frame_seq"]: _sim_t(r) for r in truth if r.get("frame_seq") is not None}

    def step_t(s: Mapping[str, Any]) -> float:
        t = seq_t.get(s.get("frame_seq"))
        return float(s["t_s"]) if t is None else t

    active = [s for s in steps if step_t(s) >= t_eng - _T_TOL_S and s.get("rmpc")]
    modes = [s["rmpc"]["mode"] for s in active]
    n = len(modes)
    return {
        "t_engaged_s": t_eng,
        "from_s": t0,
        "corner_max_px": max(vis["max_abs_u_px"], vis["max_abs_n_px"]),
        "centroid_max_px": vis["max_abs_centroid_px"],
        "frames": vis["frames"],
        "frames_outside_bound": vis["frames_outside_bound"],
        "frames_target_lost": sum(
            1 for s in steps if step_t(s) >= t0 - _T_TOL_S
            and (s.get("perception") or {}).get("status") != "ok"),
        "solves": n,
        "recovery_fraction": modes.count("recovery") / n if n else None,
        "fallbacks": modes.count("fallback"),
        "first_solve_mode": modes[0] if modes else None,
    }


def _outside(r: Mapping[str, Any], st: ReportSettings) -> tuple[bool, bool] | None:
    """(a corner outside the visible bound, the centroid outside it) for a truth record, in
    the paper's pixels; None without four finite corners."""
    c = np.asarray(r.get("corners_px") or [], dtype=float)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        return None
    scale = st.pixel_size_m / st.report_pixel_size_m
    u = -(c[:, 1] - (st.height_px - 1) / 2.0) * scale
    n = (c[:, 0] - (st.width_px - 1) / 2.0) * scale
    b = st.visible_bound_report_px
    corner = max(float(np.max(np.abs(u))), float(np.max(np.abs(n)))) > b
    return corner, max(abs(float(u.mean())), abs(float(n.mean()))) > b


def _engagement(truth: list[Mapping[str, Any]], steps: list[Mapping[str, Any]],
                st: ReportSettings) -> dict[str, Any]:
    """When OFFBOARD engaged (the emulator's mode in the ground truth), what the first RMPC
    problem was (``optimal`` = the hard problem was feasible), and visibility counted from
    :data:`ENGAGE_GRACE_S` after engagement on: frames with a corner / the centroid outside
    the visible bound, frames the target was not detected (companion steps)."""
    t_eng = next((r["t_us"] * 1e-6 for r in truth if r.get("mode") == "OFFBOARD"), None)
    first = next((s["rmpc"].get("mode") for s in steps if s.get("rmpc")), None)
    out: dict[str, Any] = {"offboard_t_s": t_eng, "first_solve_mode": first,
                           "grace_s": ENGAGE_GRACE_S}
    corner_all = centroid_all = 0
    corner_after = centroid_after = judged = 0
    t_from = None if t_eng is None else t_eng + ENGAGE_GRACE_S
    for r in truth:
        o = _outside(r, st)
        if o is None:
            continue
        corner_all += o[0]
        centroid_all += o[1]
        if t_from is not None and r["t_us"] * 1e-6 >= t_from - _T_TOL_S:
            judged += 1
            corner_after += o[0]
            centroid_after += o[1]
    out["frames_centroid_outside"] = centroid_all
    out["frames_judged"] = judged
    out["frames_corner_outside_after_grace"] = corner_after
    out["frames_centroid_outside_after_grace"] = centroid_after
    out["frames_target_lost_after_grace"] = None if t_from is None else sum(
        1 for s in steps if s.get("t_s", -math.inf) >= t_from - _T_TOL_S
        and (s.get("perception") or {}).get("status") != "ok")
    return out


def _agv(truth: list[Mapping[str, Any]]) -> dict[str, Any]:
    """The AGV's peak ground speed (m/s) and heading rate (rad/s) over the flight (truth)."""
    v = [float(np.hypot(*np.asarray(r["agv"]["vel_ned_m_s"], dtype=float)[:2]))
         for r in truth if (r.get("agv") or {}).get("vel_ned_m_s") is not None]
    w = [abs(float(r["agv"]["yaw_rate_rad_s"])) for r in truth
         if (r.get("agv") or {}).get("yaw_rate_rad_s") is not None]
    return {"max_speed_m_s": max(v) if v else None,
            "max_yaw_rate_rad_s": max(w) if w else None}


def _visibility(truth: list[Mapping[str, Any]], steps: list[Mapping[str, Any]],
                st: ReportSettings) -> dict[str, Any]:
    scale = st.pixel_size_m / st.report_pixel_size_m
    cx, cy = (st.width_px - 1) / 2.0, (st.height_px - 1) / 2.0
    max_u = max_n = 0.0
    out_frames = 0
    centroid_max = 0.0
    for r in truth:
        c = np.asarray(r.get("corners_px") or [], dtype=float)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            continue
        u_px = -(c[:, 1] - cy) * scale
        n_px = (c[:, 0] - cx) * scale
        mu, mn = float(np.max(np.abs(u_px))), float(np.max(np.abs(n_px)))
        max_u, max_n = max(max_u, mu), max(max_n, mn)
        if max(mu, mn) > st.visible_bound_report_px:
            out_frames += 1
        centroid_max = max(centroid_max, float(np.max(np.abs([u_px.mean(), n_px.mean()]))))
    lost = sum(1 for s in steps if (s.get("perception") or {}).get("status") != "ok")
    return {
        "max_abs_u_px": max_u,
        "max_abs_n_px": max_n,
        "bound_px": st.visible_bound_report_px,
        "frames_outside_bound": out_frames,
        "max_abs_centroid_px": centroid_max,
        "frames_target_lost": lost,
        "frames": len(truth),
    }


def true_features(r: Mapping[str, Any], z_star: float) -> np.ndarray | None:
    """The true ``s_e`` (4,) of a truth record: the AGV top centre in the vehicle's virtual
    frame (``s1 = x_v/z*``, ``s2 = y_v/z*``, ``s3 = z_v/z*``) and ``s4 = psi_a - psi_q``
    wrapped to (-pi/2, pi/2] (the rectangle is symmetric under a half turn)."""
    try:
        p_q = np.asarray(r["uav"]["pos_ned_m"], dtype=float)
        q = np.asarray(r["uav"]["q_wxyz"], dtype=float)
        p_a = np.asarray(r["agv"]["pos_ned_m"], dtype=float)
        yaw_a = float(r["agv"]["yaw_rad"])
    except (KeyError, TypeError):
        return None
    w, x, y, z = q
    yaw_q = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    d = p_a - p_q
    c, s = math.cos(yaw_q), math.sin(yaw_q)
    x_v, y_v = c * d[0] + s * d[1], -s * d[0] + c * d[1]
    e4 = (yaw_a - yaw_q + math.pi / 2) % math.pi - math.pi / 2
    return np.array([x_v / z_star, y_v / z_star, d[2] / z_star - 1.0, e4])


def _tracking(truth: list[Mapping[str, Any]], st: ReportSettings) -> dict[str, Any]:
    rows = []
    for r in truth:
        se = true_features(r, st.desired_depth_m)
        if se is None:
            continue
        p_q = np.asarray(r["uav"]["pos_ned_m"], dtype=float)
        p_a = np.asarray(r["agv"]["pos_ned_m"], dtype=float)
        rows.append((_sim_t(r), se, (p_a[2] - p_q[2]) - st.desired_depth_m,
                     float(np.hypot(*(p_a[:2] - p_q[:2])))))
    if not rows:
        return {"rms_se": None, "final_se": None, "rms_height_error_m": None,
                "rms_horizontal_error_m": None}
    t = np.array([r[0] for r in rows])
    se = np.array([r[1] for r in rows])
    dh = np.array([r[2] for r in rows])
    dxy = np.array([r[3] for r in rows])
    norm = np.linalg.norm(se, axis=1)
    tail = t >= t[-1] - st.settle_window_s
    settle = _settle_time(t, norm, 0.05)
    return {
        "rms_se": [float(v) for v in np.sqrt(np.mean(se**2, axis=0))],
        "final_se": [float(v) for v in se[-1]],
        "max_abs_se_last_window": [float(v) for v in np.max(np.abs(se[tail]), axis=0)],
        "settle_time_s": settle,
        "rms_height_error_m": float(np.sqrt(np.mean(dh**2))),
        "rms_horizontal_error_m": float(np.sqrt(np.mean(dxy**2))),
        "rms_height_error_after_settle_m": _rms_after(t, dh, settle),
        "rms_horizontal_error_after_settle_m": _rms_after(t, dxy, settle),
    }


def _settle_time(t: np.ndarray, norm: np.ndarray, tol: float) -> float | None:
    """First time after which ``|s_e|`` stays below ``tol`` for the rest of the flight."""
    above = np.nonzero(norm > tol)[0]
    if above.size == 0:
        return float(t[0])
    i = int(above[-1]) + 1
    return float(t[i]) if i < t.size else None


def _rms_after(t: np.ndarray, v: np.ndarray, t0: float | None) -> float | None:
    if t0 is None:
        return None
    sel = t >= t0
    return float(np.sqrt(np.mean(v[sel] ** 2))) if np.any(sel) else None


def _solver(steps: list[Mapping[str, Any]]) -> dict[str, Any]:
    recs = [s["rmpc"] for s in steps if s.get("rmpc")]
    times = np.array([r["solve_time_s"] for r in recs if r.get("solve_time_s") is not None])
    ms = times * 1e3
    return {
        "solves": len(recs),
        "failures": sum(1 for r in recs if not r["success"]),
        "optimal": sum(1 for r in recs if r["mode"] == "optimal"),
        "recoveries": sum(1 for r in recs if r["mode"] == "recovery"),
        "fallbacks": sum(1 for r in recs if r["mode"] == "fallback"),
        # rmpc.solver = "rti" (docs/reference/solver.md): steps that flew the real-time
        # iteration's plan, and steps whose RTI plan the check rejected (the full NLP then
        # solved them: their mode above is that solve's); both 0 with the full NLP
        # (a record without a status, from an older log, counts in neither)
        "rti_flown": sum(1 for r in recs if str(r.get("status", "")).startswith("rti: ")
                         and "; nlp: " not in str(r.get("status", ""))),
        "rti_to_nlp": sum(1 for r in recs if str(r.get("status", "")).startswith("rti: ")
                          and "; nlp: " in str(r.get("status", ""))),
        "median_ms": float(np.median(ms)) if ms.size else None,
        "p95_ms": float(np.percentile(ms, 95)) if ms.size else None,
        "max_ms": float(np.max(ms)) if ms.size else None,
        "mean_iterations": float(np.mean([r["iterations"] for r in recs])) if recs else None,
    }


def _latency(steps: list[Mapping[str, Any]]) -> dict[str, Any]:
    lat = np.array([s["latency_ms"] for s in steps if s.get("latency_ms") is not None])
    return {
        "frame_to_command_median_ms": float(np.median(lat)) if lat.size else None,
        "p95_ms": float(np.percentile(lat, 95)) if lat.size else None,
        "max_ms": float(np.max(lat)) if lat.size else None,
    }


def _safety(steps: list[Mapping[str, Any]]) -> dict[str, Any]:
    counts: dict[str, int] = {}
    transitions = []
    for s in steps:
        lvl = (s.get("safety") or {}).get("level", "unknown")
        counts[lvl] = counts.get(lvl, 0) + 1
        if (s.get("safety") or {}).get("changed"):
            transitions.append({"t_s": s["t_s"], "level": lvl, "reason": s["safety"]["reason"]})
    return {"steps_per_level": counts, "transitions": transitions[:200]}
