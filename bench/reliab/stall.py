"""Process stall: SIGSTOP the companion for 2 s in a realtime flight, then SIGCONT.

Meanwhile the emulator (PX4's COM_OF_LOSS_T = 1 s) must fail safe out of OFFBOARD; after it
the first command the companion sends must be built from fresh data only: its frame no later
than ``safety.max_frame_age_s`` beyond the camera's best delay, and either fresh telemetry
(age <= ``safety.telemetry_timeout_s``) or a hover built from no measurement. The backlog of
frames and telemetry queued during the stall is counted (``stale_dropped``, ``stale_inputs``).
"""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path
from typing import Any

from bench.reliab.common import (
    ProbeResult,
    children_cpu_s,
    flight,
    load_avg,
    wait_flight,
)
from companion.config import load_config
from companion.log.reader import LogReader

OFFBOARD_MAIN = 6


def run_stall(out: Path, duration_s: float = 40.0, stall_at_s: float = 4.0,
              stall_s: float = 2.0) -> ProbeResult:
    """The stall starts ``stall_at_s`` after the companion reports OFFBOARD active."""
    t_w, c0 = time.monotonic(), children_cpu_s()
    cfg = load_config()
    load0 = load_avg()
    marks: dict[str, int] = {}
    with flight(out, duration_s=duration_s, realtime=True) as f:
        def at_time() -> None:
            now = time.monotonic()
            if "active" not in marks:
                if "-> active" in (out / "companion.log").read_text():
                    marks["active"] = time.monotonic_ns()
                return
            if "stop" not in marks and now * 1e9 >= marks["active"] + stall_at_s * 1e9:
                os.kill(f.comp.pid, signal.SIGSTOP)
                marks["stop"] = time.monotonic_ns()
            elif "stop" in marks and "cont" not in marks and \
                    time.monotonic_ns() >= marks["stop"] + int(stall_s * 1e9):
                os.kill(f.comp.pid, signal.SIGCONT)
                marks["cont"] = time.monotonic_ns()

        sim_rc, comp_rc = wait_flight(f, 120.0 + 3.0 * duration_s, every=at_time,
                                      period_s=0.02)
    log = out / "flight.mcap"
    fig = stall_figures(log, marks.get("stop", 0), marks.get("cont", 0))
    fig["emulator_modes"] = _sim_modes(out / "sim.log")
    first = fig.get("first_after") or {}
    fresh = (first.get("frame_late_s") is not None
             and first["frame_late_s"] <= cfg.safety.max_frame_age_s
             and (first.get("level") == "hover" or (
                 first.get("telemetry_age_s") is not None
                 and first["telemetry_age_s"] <= cfg.safety.telemetry_timeout_s)))
    failed_safe = fig["left_offboard_during_stall"]
    ok = sim_rc == 0 and comp_rc == 0 and fresh and failed_safe and fig["stale_commands"] == 0
    return ProbeResult(
        probe="stall (SIGSTOP 2 s, realtime)",
        inputs=f"1 stall of {stall_s:.1f} s, {stall_at_s:.0f} s into OFFBOARD",
        result=(f"emulator left OFFBOARD during the stall: {failed_safe} "
                f"({fig['modes_during_stall']}); first command after: frame "
                f"{_fmt(first.get('frame_late_s'))} s late, telemetry age "
                f"{_fmt(first.get('telemetry_age_s'))} s, level {first.get('level')}, "
                f"{_fmt(first.get('after_cont_s'))} s after SIGCONT; "
                f"{fig['stale_frames_dropped']} stale frames dropped"),
        passed=ok,
        data_lost=f"{fig['stale_frames_dropped']} backlog frames refused (by design)",
        bad_commands=fig["stale_commands"],
        figures={**fig, "load_before": load0, "load_after": load_avg(), "marks_ns": marks},
        wall_s=time.monotonic() - t_w,
        cpu_s=children_cpu_s() - c0,
    )


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def stall_figures(log: Path, stop_ns: int, cont_ns: int) -> dict[str, Any]:
    cfg = load_config()
    first: dict[str, Any] | None = None
    stale_cmds = 0
    modes: list[int] = []
    stale_dropped = 0
    with LogReader(log) as r:
        for m in r.messages(topics=["/control/step", "/mavlink/in/HEARTBEAT",
                                    "/mavlink/stats"]):
            d = m.data or {}
            if m.topic == "/mavlink/stats":
                stale_dropped = int(d.get("stale_dropped", 0))
                continue
            if m.topic.endswith("HEARTBEAT"):
                # heartbeats received after the resume were sent during the stall or after
                if m.log_time_ns >= cont_ns and len(modes) < 10:
                    modes.append((int(d["fields"]["custom_mode"]) >> 16) & 0xFF)
                continue
            if m.log_time_ns < cont_ns or not d.get("sent"):
                continue
            late = d.get("frame_late_s")
            lvl = str((d.get("safety") or {}).get("level"))
            age = d.get("telemetry_age_s")
            late_frame = late is not None and late > cfg.safety.max_frame_age_s
            stale_tel = lvl in ("tracking", "terminal", "reacquire") and (
                age is None or age > cfg.safety.telemetry_timeout_s)
            stale_cmds += late_frame or stale_tel
            if first is None:
                first = {"frame_late_s": late, "telemetry_age_s": age, "level": lvl,
                         "after_cont_s": (m.log_time_ns - cont_ns) * 1e-9,
                         "reason": (d.get("safety") or {}).get("reason")}
    return {
        "first_after": first, "stale_commands": stale_cmds, "modes_during_stall": modes,
        "left_offboard_during_stall": any(md != OFFBOARD_MAIN for md in modes),
        "stale_frames_dropped": stale_dropped,
        "stall_s": (cont_ns - stop_ns) * 1e-9,
    }


def _sim_modes(sim_log: Path) -> list[str]:
    pat = re.compile(r"t=([\d.]+) s: (.*)")
    return [f"{m.group(1)} {m.group(2)}" for ln in sim_log.read_text().splitlines()
            if (m := pat.search(ln))][:20]


if __name__ == "__main__":
    import json

    print(json.dumps(run_stall(Path("out/reliability/stall")).to_json(), indent=2,
                     default=str))
