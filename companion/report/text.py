"""What the commands print at their end, for people: a few rounded lines with units and
verdicts (the report's headline), never a Python list or dict; the raw figures stay in
``report.json``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from companion.report.headline import _num, headline


def headline_lines(report: Mapping[str, Any], skip_na: bool = False) -> list[str]:
    """The headline as aligned text lines: ``PASS  label  figure  (target ...)``; with
    ``skip_na`` the rows without data are left out (a replay has no ground truth)."""
    rows = [r for r in headline(report) if not (skip_na and r.verdict == "n/a")]
    width = max((len(r.label) for r in rows), default=0)
    return [f"  {r.verdict.upper():4}  {r.label.ljust(width)}  {r.figure}"
            + ("" if r.target == "n/a" else f"  (target: {r.target})") for r in rows]


def verdict_line(report: Mapping[str, Any]) -> str:
    """One line: how many headline targets were met."""
    rows = [r for r in headline(report) if r.verdict != "n/a"]
    missed = [r.label for r in rows if r.verdict == "miss"]
    if not missed:
        return f"every headline target met ({len(rows)} judged)"
    return f"{len(missed)} of {len(rows)} headline targets missed: {', '.join(missed)}"


def _ms(v: Any) -> str:
    x = _num(v)
    return "-" if x is None else f"{x:.1f} ms"


def _cm(v: Any) -> str:
    x = _num(v)
    return "-" if x is None else f"{x * 100:.1f} cm"


def demo_summary(report: Mapping[str, Any]) -> list[str]:
    """What ``companion demo`` prints at its end: time, the headline with verdicts, the
    tracking errors over the whole flight, the solve times and the CPU, rounded and with
    units (every raw figure stays in ``report.json``)."""
    sim_t, wall = _num(report.get("sim_time_s")), _num(report.get("wall_time_s"))
    rtf = _num(report.get("real_time_factor"))
    lines = [f"  {sim_t or 0.0:.1f} s simulated in {wall or 0.0:.1f} s wall"
             + ("" if rtf is None else f" ({rtf:.1f}x real time)")
             + f", controller {report.get('controller') or '-'}"]
    lines += headline_lines(report)
    trk = report.get("tracking") or {}
    lines.append(f"  tracking over the whole flight (RMS): horizontal "
                 f"{_cm(trk.get('rms_horizontal_error_m'))}, height "
                 f"{_cm(trk.get('rms_height_error_m'))}")
    sol = report.get("solver") or {}
    lines.append(f"  solve time: median {_ms(sol.get('median_ms'))}, p95 "
                 f"{_ms(sol.get('p95_ms'))}, max {_ms(sol.get('max_ms'))}")
    cpu, emu = report.get("companion_cpu_ms_per_step"), report.get("emulator_cpu_ms_per_step")
    load = _num(report.get("load_1min"))
    start = _num(report.get("emulator_startup_cpu_s"))
    lines.append(f"  CPU per step (getrusage): companion {_ms(cpu)} (its threads and solver "
                 f"process), emulator {_ms(emu)}"
                 + ("" if start is None else f" (start-up {start:.2f} s apart)")
                 + ("" if load is None else f"; load average {load:.1f}"))
    lines.append(f"  {verdict_line(report)}")
    return lines


def _fmt(v: Any, fmt: str, unit: str = "") -> str:
    return "-" if v is None else f"{format(v, fmt)}{unit}"


def _tol(x: float) -> str:
    """``1e-6``, not Python's ``1e-06``."""
    mant, _, exp = f"{x:.0e}".partition("e")
    return f"{mant}e{int(exp)}"


def replay_summary(s: dict[str, Any]) -> list[str]:
    """The replay's result for people: the comparison's verdict, the solver, the cost; the
    raw figures stay in ``report.json``."""
    same = bool(s["identical"])
    n, changed = s["commands_compared"], s["commands_changed"]
    lines = [f"  {'PASS' if same else 'MISS'}  commands reproduced: {n - changed} of {n} "
             f"identical (max |dq| {s['max_quat_diff']:.3g}, max |dthrust| "
             f"{s['max_thrust_diff']:.3g}; tolerance {_tol(s.get('tolerance', 1e-6))})"]
    if s["first_difference_t_s"] is not None:
        lines.append(f"        first difference at t = {s['first_difference_t_s']:.2f} s")
    modes = ", ".join(f"{v} {k}" for k, v in sorted(s.get("solver_modes", {}).items()))
    lines.append(f"  solver: {modes or 'no solves'}; solve time median "
                 f"{_fmt(s.get('solve_ms_median'), '.1f', ' ms')}, p95 "
                 f"{_fmt(s.get('solve_ms_p95'), '.1f', ' ms')}")
    speed, per = s.get("speed_vs_real_time"), s.get("cpu_ms_per_step")
    start = s.get("startup_s")
    rate = "" if not speed else (f" ({speed:.1f}x real time" + (
        "" if start is None else f", start-up {start:.1f} s included") + ")")
    lines.append(f"  {s['steps']} steps ({s['perception']}) in {s['wall_time_s']:.1f} s wall"
                 f"{rate}, CPU "
                 f"{s['cpu_time_s']:.1f} s"
                 + ("" if per is None else f" ({per:.2f} ms per step, start-up and both "
                    "processes included)")
                 + f"; load average {s.get('load_1min', 0.0):.1f}")
    if not same and s.get("input_encoding") == "jpeg":
        lines.append('  the flight logged its perception input as JPEG (logging.image_encoding '
                     '= "jpeg"): lossy, so replay only approximates; record with "png" or '
                     '"raw" for exact replay')
    if s["perception_outside_crop"]:
        lines.append(f"  perception read outside the logged crop in "
                     f"{s['perception_outside_crop']} steps: not exact there")
    if s["log"].get("truncated"):
        lines.append(f"  log was cut short: {s['log']['messages_recovered']} messages "
                     "recovered")
    return lines
