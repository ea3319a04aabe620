"""One campaign run: a lockstep flight (``companion demo``) in its own folder, scored into a row.

:func:`run_flight` is what a Dask worker executes. It never raises: a flight that fails (a
config key a program refuses, a process that dies, a flight that does not finish) is a row
with ``status = "error"`` and the error's first line, the traceback in ``error.txt``. The row
is written to ``OUT/runs/RUN_ID/result.json`` last (atomically), so a folder with a
``result.json`` is a finished run and a resumed campaign skips it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import resource
import time
import traceback
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from companion.campaign.scenarios import SCENARIO_NAME, RunSpec

__all__ = ["RESULT_FILE", "finished_result", "metrics_row", "rescore", "run_flight"]

RESULT_FILE = "result.json"
#: wall time a flight may take (s): generous, a shared machine can run lockstep at 1/20 of real
#: time; a flight that hangs is still stopped
BUDGET_BASE_S = 300.0
BUDGET_PER_SIM_S = 30.0


def finished_result(spec: RunSpec) -> dict[str, Any] | None:
    """The row of a run already finished in ``spec.out_dir``, if any."""
    p = Path(spec.out_dir) / RESULT_FILE
    try:
        row: dict[str, Any] = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return row


_MPC_MODES = ("optimal", "recovery", "fallback")


def rescore(row: dict[str, Any], out_dir: str | Path) -> dict[str, Any]:
    """``row`` with its metrics recomputed from the run's ``report.json`` (when it was flown
    to the end and the report is there): metric definitions can change without flying again."""
    p = Path(out_dir) / "report.json"
    row = {**row, "lockstep_timeouts": _lockstep_timeouts(Path(out_dir) / "sim.log")}
    if row.get("status") != "ok" or not p.is_file():
        return row
    try:
        report = json.loads(p.read_text())
    except ValueError:
        return row
    return {**row, **metrics_row(report)}


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _spec_columns(spec: RunSpec) -> dict[str, Any]:
    s = spec.start
    return {
        "run_id": spec.run_id, "controller": spec.controller, "scenario": spec.scenario,
        "seed": spec.seed, "path": spec.path, "speed_scale": spec.speed_scale,
        "duration_s": spec.duration_s,
        "nominal_peak_speed_m_s": round(spec.nominal_peak_speed_m_s, 4),
        "nominal_peak_yaw_rate_rad_s": round(spec.nominal_peak_yaw_rate_rad_s, 4),
        "start_x_m": s.uav_pose[0], "start_y_m": s.uav_pose[1], "start_height_m": s.height_m,
        "start_yaw_error_rad": s.yaw_error_rad, "start_centroid_u_px": s.centroid_px[0],
        "start_centroid_n_px": s.centroid_px[1], "start_max_corner_px": s.max_corner_px,
    }


def metrics_row(report: Mapping[str, Any]) -> dict[str, Any]:
    """The per-run figures of a flight's ``report.json`` (``companion/report/figures.py``).

    ``corners_in_view`` / ``centroid_in_view``: no frame with a corner / the centroid outside
    the visible bound from 1 s after OFFBOARD engaged on (ground truth); ``target_kept``: the
    companion detected the target on every step from then on. ``first_feasible``: the first
    RMPC problem was the hard one (mode ``optimal``); ``None`` for a controller without one.
    ``first_feasible_engaged``: the same for the first problem solved in OFFBOARD, the first
    whose input is applied (the first problem of the flight is solved during the pre-flight
    setpoint stream, ~1 s earlier, and never applied; recursive feasibility starts at the first
    applied solve)."""
    vis = report.get("visibility") or {}
    eng = report.get("engagement") or {}
    sol = report.get("solver") or {}
    trk = report.get("tracking") or {}
    agv = report.get("agv") or {}
    lat = report.get("latency") or {}
    solves = int(sol.get("solves") or 0)
    rec = int(sol.get("recoveries") or 0)
    first = eng.get("first_solve_mode")
    corner_after = eng.get("frames_corner_outside_after_grace")
    centroid_after = eng.get("frames_centroid_outside_after_grace")
    lost_after = eng.get("frames_target_lost_after_grace")
    engaged = eng.get("offboard_t_s") is not None
    engd = report.get("engaged") or {}
    rms = trk.get("rms_se") or [None] * 4
    corner_max = max((v for v in (_num(vis.get("max_abs_u_px")), _num(vis.get("max_abs_n_px")))
                      if v is not None), default=None)
    return {
        "sim_time_s": _num(report.get("sim_time_s")),
        "frames": vis.get("frames"),
        "agv_max_speed_m_s": _num(agv.get("max_speed_m_s")),
        "agv_max_yaw_rate_rad_s": _num(agv.get("max_yaw_rate_rad_s")),
        "offboard_t_s": _num(eng.get("offboard_t_s")),
        "first_solve_mode": first,
        # only an MPC has a first problem (the IBVS law logs mode "law")
        "first_feasible": (first == "optimal") if first in _MPC_MODES else None,
        "first_solve_mode_engaged": engd.get("first_solve_mode"),
        "first_feasible_engaged": (engd.get("first_solve_mode") == "optimal")
        if engd.get("first_solve_mode") in _MPC_MODES else None,
        "controller_kind": report.get("controller"),
        "corner_max_px": corner_max,
        "corner_max_after_grace_px": _num(engd.get("corner_max_px")),
        "recovery_fraction_engaged": _num(engd.get("recovery_fraction")),
        "centroid_max_px": _num(vis.get("max_abs_centroid_px")),
        "frames_corner_outside": vis.get("frames_outside_bound"),
        "frames_centroid_outside": eng.get("frames_centroid_outside"),
        "frames_target_lost": vis.get("frames_target_lost"),
        "frames_judged": eng.get("frames_judged"),
        "frames_corner_outside_after_grace": corner_after,
        "frames_centroid_outside_after_grace": centroid_after,
        "frames_target_lost_after_grace": lost_after,
        "corners_in_view": engaged and corner_after == 0,
        "centroid_in_view": engaged and centroid_after == 0,
        "target_kept": engaged and lost_after == 0,
        "solves": solves,
        "optimal": sol.get("optimal"),
        "recoveries": rec,
        "fallbacks": sol.get("fallbacks"),
        "solver_failures": sol.get("failures"),
        "recovery_fraction": rec / solves if solves else None,
        "solve_median_ms": _num(sol.get("median_ms")),
        "solve_p95_ms": _num(sol.get("p95_ms")),
        "solve_max_ms": _num(sol.get("max_ms")),
        "rms_s1": _num(rms[0]), "rms_s2": _num(rms[1]), "rms_s3": _num(rms[2]),
        "rms_s4": _num(rms[3]),
        "rms_height_error_m": _num(trk.get("rms_height_error_m")),
        "rms_horizontal_error_m": _num(trk.get("rms_horizontal_error_m")),
        "settle_time_s": _num(trk.get("settle_time_s")),
        "latency_median_ms": _num(lat.get("frame_to_command_median_ms")),
    }


def _lockstep_timeouts(sim_log: Path) -> int | None:
    """Steps the emulator took without the companion's setpoint (its end-of-run line)."""
    try:
        m = re.search(r"done: .* (\d+) lockstep timeouts", sim_log.read_text())
    except OSError:
        return None
    return int(m.group(1)) if m else None


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def run_flight(spec: RunSpec) -> dict[str, Any]:
    """Fly ``spec`` (unless already finished) and return its row (see the module docstring)."""
    done = finished_result(spec)
    if done is not None:
        return done
    from companion.flight import run_demo

    out = Path(spec.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "run.json").write_text(json.dumps(dataclasses.asdict(spec), indent=2))
    row = _spec_columns(spec)
    t0 = time.monotonic()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        report = run_demo(Path(spec.config), SCENARIO_NAME, spec.duration_s, out,
                          list(spec.overrides), [], plots=False,
                          budget_s=BUDGET_BASE_S + BUDGET_PER_SIM_S * spec.duration_s)
        row.update(status="ok", error="", **metrics_row(report))
    except Exception as exc:  # a run that fails is a row, never the campaign's end
        msg = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        row.update(status="error", error=f"{type(exc).__name__}: {msg}"[:300])
        (out / "error.txt").write_text(traceback.format_exc())
    finally:
        if not spec.keep_log:
            (out / "flight.mcap").unlink(missing_ok=True)
        (out / ".companion-ready").unlink(missing_ok=True)
    row["lockstep_timeouts"] = _lockstep_timeouts(out / "sim.log")
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    row["wall_s"] = round(time.monotonic() - t0, 3)
    row["cpu_s"] = round((ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime), 3)
    row["worker_pid"] = os.getpid()
    _write_atomic(out / RESULT_FILE, json.dumps(row, indent=2))
    return row
